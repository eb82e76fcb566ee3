"""Shared test helpers: a tiny untrained policy for the simulated tasks, and a real uvicorn service
on 127.0.0.1 that stops by itself."""

import signal
import socket
import subprocess
import threading
import time

import httpx
import numpy as np
import torch
import uvicorn

from policy.checkpoint import save_calibration, save_policy
from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from server.app import create_app
from sim.registry import make_task


def tiny_policy(task: str = "lift-cube") -> DiffusionPolicy:
    """An untrained tiny policy: its actions are noise around the lift workspace, so any success
    comes from the operator."""
    torch.manual_seed(0)
    obs_dim = make_task(task).obs_spec.dim
    p = DiffusionPolicy(
        DiffusionPolicyConfig(obs_dim=obs_dim, network="mlp", mlp_hidden=16, step_embed_dim=8, num_inference_steps=2)
    )
    rng = np.random.default_rng(0)
    acts = np.concatenate(
        [rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0], (64, 3)), np.tile([0, 1, 0, 1, 0, 0, -1], (64, 1))], 1
    )
    p.fit_normalizers(rng.normal(size=(64, obs_dim)), acts)
    return p.eval()


def tiny_policy_folder(folder, task: str, threshold: float):
    """``tiny_policy`` saved as a policy folder with ``threshold`` as its calibration, for ``denoising``
    (calibration.json) and for ``spread`` (its signal folder, spread in the action space's own units)."""
    from policy.signals import make_signal, save_signal

    policy = tiny_policy(task)
    save_policy(policy, folder, {"task": task})
    save_calibration(folder, {"threshold": threshold, "quantile": 0.95, "samples": 0})
    spread = make_signal("spread", policy, {"num_samples": 8})
    spread.calibration = {"threshold": threshold, "quantile": 0.95, "samples": 0, "spread_scale": 1.0}
    save_signal(spread, folder, {"command": "tests.helpers.tiny_policy_folder"})
    return folder


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(fn, timeout: float = 30.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = fn()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("condition not met in time")


def stop_process(proc, timeout: float = 60.0) -> None:
    """SIGTERM, then SIGKILL if ``proc`` (a ``subprocess.Popen``) has not exited within ``timeout``."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Service:
    """``create_app(settings)`` under a real uvicorn in a thread; ready on enter, stopped on exit."""

    def __init__(self, settings):
        self.settings = settings
        self.url = f"http://127.0.0.1:{settings.port}"
        self.app = create_app(settings)
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=settings.port, log_level="warning")
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        deadline = time.time() + 120
        while time.time() < deadline:
            try:
                if httpx.get(self.url + "/readyz").status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError("service did not become ready")

    def app_state(self):
        """The running app's state (the services its lifespan built)."""
        return self.app.state

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=60)


class KinematicTask:
    """A light stand-in for a simulated task (no physics engine): the end effector jumps to each
    commanded target, the observation is the lift layout's size with the pose in front. Episodes end
    after ``horizon`` counted steps (holds do not count, as in ``Task.step``), in success only when
    ``success_z`` is set and the end effector is at or above it. Fleet unit tests run on it in-process."""

    name = "lift-cube"

    def __init__(self, horizon: int = 1000, success_z: float | None = None):
        spec = make_task("lift-cube")
        self.action_space, self.obs_spec, self.horizon = spec.action_space, spec.obs_spec, horizon
        self.success_z = success_z
        self.t = self.clock = 0
        self.action = None
        self.closed = False

    def reset(self, seed: int):
        rng = np.random.default_rng(seed)
        self.t = self.clock = 0
        self.action = self.action_space.make_action(np.array([rng.uniform(-0.05, 0.05), 0.0, 1.0]), np.eye(3), -1.0)
        return self.observe()

    def step(self, action, hold: bool = False):
        from sim.env import StepResult

        self.action = self.action_space.validate(action)
        self.t += 1
        self.clock += 0 if hold else 1
        success = self.success_z is not None and self.action[2] >= self.success_z
        return StepResult(self.observe(), success, success or self.clock >= self.horizon, self.t, self.clock)

    def observe(self):
        obs = np.zeros(self.obs_spec.dim)
        obs[:10] = self.action
        return obs

    def ee_pose(self):
        from sim.rotations import rot6d_to_mat

        return self.action[:3].copy(), rot6d_to_mat(self.action[3:9])

    def hold_action(self):
        return self.action.copy()

    def joint_positions(self):
        return None  # no simulated scene to pose

    def gripper_opening(self):
        return 0.08 if self.action[9] < 0 else 0.0

    def object_poses(self):
        return {"cube": (np.array([0.0, 0.0, 0.82]), np.array([0.0, 0.0, 0.0, 1.0]))}

    def privileged(self):
        return {}

    def episode_info(self):
        return {}

    def close(self):
        self.closed = True

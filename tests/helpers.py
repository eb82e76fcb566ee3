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
from service.app import create_app
from sim.registry import make_task


def state_equal(a: DiffusionPolicy, b: DiffusionPolicy) -> bool:
    """Whether two policies hold the same weights, tensor for tensor."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


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


def save_tiny_signals(policy, folder, threshold: float, info: dict | None = None) -> None:
    """``spread`` (in the action space's own units) with ``threshold``, and the fleet's default,
    ``choice-stall``, whose ``choice`` has ``threshold`` (metres): its gate is never passed, so every scene
    counts as familiar (the untrained policy's observations lie anywhere)."""
    from policy.signals import make_signal, save_signal

    spread_cal = {"threshold": threshold, "quantile": 0.95, "samples": 0, "spread_scale": 1.0}
    spread = make_signal("spread", policy, {"num_samples": 8})
    spread.calibration = spread_cal
    save_signal(spread, folder, info)
    choice = make_signal("choice-stall", policy, {"num_samples": 8, "novelty_gate": 1e9})
    choice.calibration = {
        "threshold": 1.0,
        "choice": {"threshold": threshold, "stride": 0.01},
        "stall": {"threshold": 0.5, "stride": 0.01},
    }
    save_signal(choice, folder, info)


def tiny_policy_folder(folder, task: str, threshold: float, obs_labels: list[str] | None = None):
    """``tiny_policy`` saved as a policy folder with ``threshold`` as its calibration, for ``denoising``
    (calibration.json), ``spread`` and ``choice-stall`` (``save_tiny_signals``). ``obs_labels``: the
    observation layout its config.json records (``hitl train`` records the task's); None: none, as
    checkpoints written before layouts were recorded."""
    policy = tiny_policy(task)
    save_policy(policy, folder, {"task": task} | ({"obs_labels": obs_labels} if obs_labels is not None else {}))
    save_calibration(folder, {"threshold": threshold, "quantile": 0.95, "samples": 0})
    save_tiny_signals(policy, folder, threshold, {"command": "tests.helpers.tiny_policy_folder"})
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
    with_images = False  # no renderer: its frames carry no camera images

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

    def observation(self):  # what a state-based policy observes (``Task.observation``)
        return self.observe()

    def ee_pose(self):
        from sim.rotations import rot6d_to_mat

        return self.action[:3].copy(), rot6d_to_mat(self.action[3:9])

    def hold_action(self):
        return self.action.copy()

    def joint_positions(self):
        return None  # no simulated scene to pose

    def placed_poses(self):
        return {}

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


def finetunable_policy_folder(root, task: str = "lift-cube", obs_labels: list[str] | None = None):
    """``tiny_policy`` as a policy folder a fine-tuning job can use: pretrained (on paper) on 5 synthetic
    episodes under ``root/demos`` (4 training, 1 validation, as its config.json says), with a
    calibration and the signals of ``save_tiny_signals`` to recalibrate. ``obs_labels``: the observation
    layout its config.json and its episodes record (None: none, as before layouts were recorded)."""
    from storage import keys
    from storage.episodes import EpisodeWriter

    obs_dim = make_task(task).obs_spec.dim
    demos = root / "demos"
    rng = np.random.default_rng(1)
    for i in range(5):
        meta = {"task": task, "seed": i} | ({"obs_labels": obs_labels} if obs_labels is not None else {})
        w = EpisodeWriter(demos / f"{task}_seed{i:06d}.mcap", meta, object_names=[])
        for t in range(6):
            act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [-1.0]]
            w.write_step(
                t,
                rng.normal(size=obs_dim),
                act,
                act[:3],
                np.array([0, 0, 0, 1.0]),
                0.04,
                t == 5,
                keys.SOURCE_EXPERT,
                {},
            )
        w.finish(True, 6, "success")
    policy = tiny_policy(task)
    folder = root / "policies" / task
    names = sorted(p.name for p in demos.glob("*.mcap"))
    dataset = {"folder": str(demos), "train_episodes": names[:4], "val_episodes": names[4:]}
    info = {"task": task, "dataset": dataset, "command": "tests.helpers"}
    save_policy(policy, folder, info | ({"obs_labels": obs_labels} if obs_labels is not None else {}))
    save_calibration(
        folder, {"threshold": 1e9, "quantile": 0.95, "samples": 0, "uncertainty": {"num_samples": 16, "max_modes": 2}}
    )
    save_tiny_signals(policy, folder, 1e9, {})
    return folder


def write_segment(
    path, obs_dim: int, steps: int = 5, seed: int = 0, task: str = "lift-nut", obs_labels: list[str] | None = None
):
    """A closed takeover segment of ``steps`` random (observation, absolute action) pairs; ``obs_labels``:
    the observation layout its metadata records, as the fleet's do (None: none, as older segments)."""
    from storage.segments import SegmentWriter

    rng = np.random.default_rng(seed)
    meta = {"robot": 0, "task": task, "operator": "op"} | ({"obs_labels": obs_labels} if obs_labels is not None else {})
    w = SegmentWriter(path, meta)
    for _ in range(steps):
        act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [1.0]]
        w.write_step(rng.normal(size=obs_dim), {"dpos": [0, 0, 0.01]}, act, act, act[:3], [0, 0, 0, 1.0], 0.1)
    w.close("closed", "hand-back")
    return path

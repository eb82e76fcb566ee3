"""Shared test helpers: a tiny untrained policy for the simulated tasks, and a real uvicorn service
on 127.0.0.1 that stops by itself."""

import socket
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
    """``tiny_policy`` saved as a policy folder with ``threshold`` as its calibration."""
    save_policy(tiny_policy(task), folder, {"task": task})
    save_calibration(folder, {"threshold": threshold, "quantile": 0.95, "samples": 0})
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


class Service:
    """``create_app(settings)`` under a real uvicorn in a thread; ready on enter, stopped on exit."""

    def __init__(self, settings):
        self.settings = settings
        self.url = f"http://127.0.0.1:{settings.port}"
        self.server = uvicorn.Server(
            uvicorn.Config(create_app(settings), host="127.0.0.1", port=settings.port, log_level="warning")
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

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=60)

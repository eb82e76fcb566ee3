"""The simulated operator as an API client: it watches the queue, claims the most urgent robot,
drives it with the task's scripted expert from the operator view, and hands back.

It uses only the public REST API, so it is also an example client for users.
"""

from __future__ import annotations

import logging
import time

import httpx
import numpy as np
from scipy.spatial.transform import Rotation

from sim.registry import make_expert
from sim.spaces import TeleopLimits

log = logging.getLogger("hitl.operator_bot")
LIMITS = TeleopLimits()


class ViewTask:
    """What the scripted experts read from a task, rebuilt from the operator view."""

    def __init__(self, view: dict) -> None:
        self.update(view)

    def update(self, view: dict) -> None:
        self.name = view["task"]
        pose = view["pose"]
        self._pos = np.asarray(pose["position"], dtype=np.float64)
        self._rot = Rotation.from_quat(pose["quaternion"]).as_matrix()
        self._privileged = {k: np.asarray(v) if isinstance(v, list) else v for k, v in view["goal"].items()}
        self._gripper = float(view["gripper"]) if view.get("gripper") is not None else 0.08

    def gripper_opening(self) -> float:
        return self._gripper

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._pos.copy(), self._rot.copy()

    def privileged(self) -> dict:
        return dict(self._privileged)


class OperatorBot:
    def __init__(self, url: str, token: str, heartbeat_s: float = 1.0, timeout: float = 10.0) -> None:
        self.api = url.rstrip("/") + "/api/v1"
        self.client = httpx.Client(headers={"Authorization": f"Bearer {token}"}, timeout=timeout)
        self.heartbeat_s = heartbeat_s
        self.takeovers = 0
        self.commands = 0

    def close(self) -> None:
        self.client.close()

    def _get(self, path: str):
        r = self.client.get(self.api + path)
        r.raise_for_status()
        return r.json()

    def next_request(self) -> dict | None:
        return next((r for r in self._get("/assistance") if r["holder"] is None), None)

    def takeover(self, robot_id: int, seed: int = 0, max_steps: int = 1000) -> int:
        """Claims ``robot_id`` and drives it until the service hands control back; returns steps driven."""
        r = self.client.post(f"{self.api}/robots/{robot_id}/claim")
        if r.status_code in (404, 409):  # someone else was faster, or the request is gone
            return 0
        r.raise_for_status()
        view = self._get(f"/robots/{robot_id}/view")
        task = ViewTask(view)
        expert = make_expert(task.name)
        expert.resume(task, np.random.default_rng([seed, robot_id]))  # pick up where the scene stands
        steps, last_beat = 0, time.monotonic()
        try:
            while steps < max_steps:
                detail = self._get(f"/robots/{robot_id}")
                if detail["mode"] != "teleop":
                    break
                task.update(self._get(f"/robots/{robot_id}/view"))
                cmd = expert.act(task).clamped(LIMITS)  # send what the robot will execute
                body = {
                    "delta_pos": [float(x) for x in cmd.delta_pos],
                    "delta_rot": [float(x) for x in cmd.delta_rot],
                    "gripper": float(cmd.gripper),
                }
                r = self.client.post(f"{self.api}/robots/{robot_id}/command", json=body)
                if r.status_code == 409:  # lease lost or control handed back
                    break
                r.raise_for_status()
                self.commands += 1
                steps += 1
                self._wait_applied(robot_id, detail["assisted_steps"])
                if time.monotonic() - last_beat > self.heartbeat_s:
                    self.client.post(f"{self.api}/robots/{robot_id}/heartbeat")
                    last_beat = time.monotonic()
        finally:
            self.takeovers += 1
        return steps

    def _wait_applied(self, robot_id: int, before: int, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            d = self._get(f"/robots/{robot_id}")
            if d["assisted_steps"] > before or d["mode"] != "teleop":
                return
            time.sleep(0.01)

    def run(self, max_takeovers: int | None = None, idle_sleep: float = 0.2, stop=None) -> None:
        """Serves the queue until ``max_takeovers`` or ``stop()`` returns True."""
        while (max_takeovers is None or self.takeovers < max_takeovers) and not (stop and stop()):
            req = self.next_request()
            if req is None:
                time.sleep(idle_sleep)
                continue
            steps = self.takeover(req["robot_id"], seed=self.takeovers)
            log.info("robot %d: drove %d steps", req["robot_id"], steps)

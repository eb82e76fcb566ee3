"""``OperatorView``: what a human operator sees of one robot, in the shape the scripted experts read.

The scripted experts (``sim.experts``) drive a task through ``ee_pose``, ``gripper_opening`` and
``privileged`` (the scene as a camera shows it: object poses, handles, the goal). A human operator
sees exactly that and nothing more, so the simulated operator drives from an ``OperatorView`` built
from the robot's ``RobotFrame`` (in-process benchmarks) or from the service's
``GET /robots/{id}/view`` (``hitl operator-bot``): both paths give the expert the same inputs.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sim.frame import RobotFrame

OPEN_GAP = 0.08  # metres: the finger gap assumed when a view reports none


class ViewUnavailable(Exception):
    """The view has no scene to drive: no frame yet, or the robot is not under teleop."""


class OperatorView:
    """The expert-facing task interface over an operator view (``update`` refreshes it each step)."""

    def __init__(self, name: str, pos: np.ndarray, rot: np.ndarray, gripper: float, goal: dict) -> None:
        self.name = name
        self._pos = np.asarray(pos, dtype=np.float64).copy()
        self._rot = np.asarray(rot, dtype=np.float64).copy()
        self._gripper = float(gripper)
        self._privileged = {k: np.asarray(v) if isinstance(v, list) else v for k, v in (goal or {}).items()}

    @classmethod
    def from_frame(cls, task_name: str, frame: RobotFrame) -> OperatorView:
        return cls(task_name, frame.pos, frame.rot, frame.gripper, frame.goal)

    @classmethod
    def from_api(cls, view: dict) -> OperatorView:
        """From the JSON of ``GET /robots/{id}/view``; raises ViewUnavailable when there is no scene."""
        pose = view.get("pose")
        if pose is None or view.get("mode") not in (None, "teleop"):
            raise ViewUnavailable(f"robot {view.get('robot_id')} is {view.get('mode')} with pose {pose}")
        gripper = float(view["gripper"]) if view.get("gripper") is not None else OPEN_GAP
        rot = Rotation.from_quat(pose["quaternion"]).as_matrix()
        return cls(view["task"], pose["position"], rot, gripper, view.get("goal") or {})

    def gripper_opening(self) -> float:
        return self._gripper

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._pos.copy(), self._rot.copy()

    def privileged(self) -> dict:
        return dict(self._privileged)

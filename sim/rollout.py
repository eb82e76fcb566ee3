"""The expert control loop, as a plain function."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import Task
from sim.experts import Expert


@dataclass(frozen=True)
class StepRecord:
    """One control step: the observation before the action and what followed."""

    t: int
    obs: np.ndarray
    action: np.ndarray
    ee_pos: np.ndarray
    ee_quat: np.ndarray  # xyzw
    gripper: float  # finger gap (m)
    success: bool  # after the step
    objects: dict[str, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class EpisodeResult:
    success: bool
    steps: int
    metadata: dict


def run_expert_episode(
    task: Task,
    expert: Expert,
    seed: int,
    on_step: Callable[[StepRecord], None] | None = None,
) -> EpisodeResult:
    """Resets ``task`` with ``seed`` and lets ``expert`` act until success or the horizon."""
    obs = task.reset(seed)
    expert.reset(task, np.random.default_rng([seed, 2]))
    success, t = False, 0
    while t < task.horizon:
        pos, rot = task.ee_pose()
        objects = task.object_poses()
        gap = task.gripper_opening()
        action = task.teleop(expert.act(task)).action
        result = task.step(action)
        if on_step is not None:
            on_step(StepRecord(t, obs, action, pos, Rotation.from_matrix(rot).as_quat(), gap, result.success, objects))
        obs, success, t = result.obs, result.success, result.t
        if result.done:
            break
    return EpisodeResult(success=success, steps=t, metadata=task.metadata() | {"seed": seed, "expert": expert.name})

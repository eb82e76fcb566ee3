"""The expert control loop, as a plain function."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import Task
from sim.experts import Expert
from sim.rotations import mat_to_rot6d, rot6d_to_mat


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
    images: dict[str, np.ndarray] | None = (
        None  # what the policy's cameras saw before the action (``Task.with_images``)
    )


@dataclass(frozen=True)
class EpisodeResult:
    success: bool
    steps: int
    metadata: dict


@dataclass(frozen=True)
class ExecutionNoise:
    """DART-style noise: the executed target is perturbed, the recorded action stays the expert's.

    pos: std of the target position offset (m); rot: std of a yaw rotation of the target (rad).
    The expert, closed-loop, then demonstrates how to recover from the states the noise causes.
    """

    pos: float = 0.0
    rot: float = 0.0

    def __post_init__(self) -> None:
        for name in ("pos", "rot"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0 <= v <= 0.5):
                raise ValueError(f"ExecutionNoise.{name} must be in [0, 0.5], got {v!r}")

    def apply(self, action: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = action.copy()
        out[0:3] += rng.normal(0.0, self.pos, 3)
        yaw = Rotation.from_euler("z", rng.normal(0.0, self.rot))
        out[3:9] = mat_to_rot6d((yaw * Rotation.from_matrix(rot6d_to_mat(action[3:9]))).as_matrix())
        return out


def run_expert_episode(
    task: Task,
    expert: Expert,
    seed: int,
    on_step: Callable[[StepRecord], None] | None = None,
    noise: ExecutionNoise | None = None,
) -> EpisodeResult:
    """Resets ``task`` with ``seed`` and lets ``expert`` act until success or the horizon."""
    obs = task.reset(seed)
    expert.reset(task, np.random.default_rng([seed, 2]))
    noise_rng = np.random.default_rng([seed, 3])
    success, t = False, 0
    while t < task.horizon:
        pos, rot = task.ee_pose()
        objects = task.object_poses()
        gap = task.gripper_opening()
        images = task.images() if task.with_images else None
        action = task.teleop(expert.act(task)).action
        executed = noise.apply(action, noise_rng) if noise is not None else action
        result = task.step(executed)
        if on_step is not None:
            on_step(
                StepRecord(
                    t, obs, action, pos, Rotation.from_matrix(rot).as_quat(), gap, result.success, objects, images
                )
            )
        obs, success, t = result.obs, result.success, result.t
        if result.done:
            break
    return EpisodeResult(success=success, steps=t, metadata=task.metadata() | {"seed": seed, "expert": expert.name})

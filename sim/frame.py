"""``RobotFrame``: what one robot reports after a reset or a step, the one type every loop reads.

The fleet's robot workers send it, in-process rollouts build it from their ``Task``, and the
controller (``policy.controller``) acts on it. Arrays are plain numpy, so a frame pickles across a
process boundary.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import StepResult, Task


@dataclass(frozen=True)
class RobotFrame:
    """One robot's state after a reset (``t == 0``) or a control step.

    obs: (obs_dim,) float32 observation; hold: (10,) the action that holds the current pose and the
    gripper command in force; pos: (3,) end-effector position (m, world frame); rot: (3, 3) its
    rotation matrix; quat: (4,) the same rotation as a quaternion (x, y, z, w); gripper: finger gap
    (m); bodies: object name -> (position (3,), quaternion xyzw (4,)); goal: what a human operator
    sees of the scene's goal (plain JSON values); t: steps since the reset; clock: those of them that
    count against the horizon (holds do not); horizon: the clock's limit (the task's); success / done:
    the task's outcome after this step;
    info: the task's episode details, set once ``done``; qpos: (nq,) the simulation's joint positions
    and placed: model body -> (position, quaternion xyzw) of the bodies the task places without a joint
    (``Task.placed_poses``), together enough for a viewer holding the task's model to pose every body
    (``pose_model``: the console's scene, the camera views); images: what the policy's cameras see after
    this step (``Task.images``: camera name -> (size, size, 3) uint8), when the task renders them
    (``Task.with_images``), else empty.
    """

    obs: np.ndarray
    hold: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    quat: np.ndarray
    gripper: float
    bodies: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    goal: dict = field(default_factory=dict)
    t: int = 0
    clock: int = 0
    horizon: int = 0
    success: bool = False
    done: bool = False
    info: dict = field(default_factory=dict)
    qpos: np.ndarray | None = None
    placed: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def gripper_command(self) -> float:
        """The gripper command in force (-1 open .. +1 closed)."""
        return float(self.hold[9])

    @classmethod
    def from_task(cls, task: Task, result: StepResult | None = None) -> RobotFrame:
        """The frame of ``task`` as it stands: after ``result`` (a step), or right after a reset."""
        pos, rot = task.ee_pose()
        done = bool(result.done) if result is not None else False
        return cls(
            obs=(task.observation() if result is None else result.obs).astype(np.float32),
            hold=task.hold_action().astype(np.float64),
            pos=pos,
            rot=rot,
            quat=Rotation.from_matrix(rot).as_quat(),
            gripper=float(task.gripper_opening()),
            bodies={k: (np.asarray(p), np.asarray(q)) for k, (p, q) in task.object_poses().items()},
            goal={k: _jsonable(v) for k, v in (task.privileged() or {}).items()},
            t=0 if result is None else int(result.t),
            clock=0 if result is None else int(result.clock),
            horizon=int(task.horizon),
            success=bool(result.success) if result is not None else False,
            done=done,
            info=task.episode_info() if done else {},
            qpos=task.joint_positions(),
            placed=task.placed_poses(),
            images=task.images() if task.with_images else {},
        )


def pose_model(model, data, qpos: np.ndarray, placed: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Poses a viewer's own copy of a task's model (``Task.mj_model``) and its data as a frame shows them:
    the bodies placed without a joint (``RobotFrame.placed``: children of the world, moved in the model)
    and the joints (``qpos``), then kinematics, no physics step. ValueError if the model lacks a body or
    ``qpos`` does not fit it."""
    import mujoco  # here, not at import: a renderer's process chooses its OpenGL back end before mujoco loads

    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.shape != (model.nq,):
        raise ValueError(f"qpos has shape {qpos.shape}, the model {model.nq} joint positions")
    for name, (pos, quat) in placed.items():
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            raise ValueError(f"the model has no body {name!r}")
        model.body_pos[body] = pos
        model.body_quat[body] = np.roll(np.asarray(quat, dtype=np.float64), 1)  # (x, y, z, w) -> (w, x, y, z)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v

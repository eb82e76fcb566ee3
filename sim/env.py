"""The robosuite scene shared by every task and the ``Task`` base class.

A ``Task`` owns one robosuite environment (Panda arm, OSC controller with
absolute world-frame pose input, no cameras) and adds what the product needs:
a flat observation vector with named components, an ``ActionSpace``, a
horizon, a success check, a seeded reset, privileged state for the scripted
experts, and object poses for 3D playback.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.rotations import mat_to_rot6d, rot6d_to_mat, rot6d_to_rotvec, wxyz_to_xyzw
from sim.spaces import ActionSpace, TeleopCommand, TeleopTarget
from sim.vision import CameraSpec, PolicyCameras

TABLE_TOP_Z = 0.8
TABLE_FULL_SIZE = (0.8, 0.8, 0.05)
CONTROL_FREQ = 20
EE_FRAME = "ee"

# what a policy that sees cameras observes besides them: the robot's own state, as the paper's policies
# (``Task.sees_cameras``): no object pose, bounding box, ray or visibility flag
ROBOT_OBS_PARTS = (("eef_pos", 3), ("eef_rot6d", 6), ("gripper_qpos", 2))

# Robot joint noise at reset (radians, gaussian), seeded per episode; a task may set its own
# (``Task.init_joint_noise``).
INIT_JOINT_NOISE = 0.02


def _quiet_robosuite() -> None:
    """robosuite warns about private macros and optional robots on import, and logs every env.

    Its logger's level is reset when robosuite is imported, so a filter (which
    survives that) keeps only errors.
    """
    logger = logging.getLogger("robosuite_logs")
    if not any(getattr(f, "_hitl", False) for f in logger.filters):
        only_errors = logging.Filter()
        only_errors.filter = lambda record: record.levelno >= logging.ERROR  # type: ignore[method-assign]
        only_errors._hitl = True  # type: ignore[attr-defined]
        logger.addFilter(only_errors)


@dataclass(frozen=True)
class ObsSpec:
    """Names and sizes of the observation vector's components, in order."""

    parts: tuple[tuple[str, int], ...]

    @property
    def dim(self) -> int:
        return sum(n for _, n in self.parts)

    def labels(self) -> list[str]:
        """One name per observation dimension: ``part`` or ``part[i]``."""
        return [name if n == 1 else f"{name}[{i}]" for name, n in self.parts for i in range(n)]

    @property
    def has_ee_pose(self) -> bool:
        """The observation holds the end-effector pose (``eef_pos`` and ``eef_rot6d``): ``ee_pose`` works."""
        return {"eef_pos", "eef_rot6d"} <= {name for name, _ in self.parts}

    def ee_pose(self, states: np.ndarray) -> np.ndarray:
        """(T, 7) end-effector position + quaternion xyzw from (T, dim) observations, from their
        ``eef_pos`` and ``eef_rot6d`` parts (``has_ee_pose``)."""
        if not self.has_ee_pose:
            raise ValueError("the observation has no eef_pos and eef_rot6d parts")
        parts = self.slices()
        states = np.asarray(states, np.float64).reshape(-1, self.dim)
        quat = Rotation.from_matrix(rot6d_to_mat(states[:, parts["eef_rot6d"]])).as_quat().reshape(-1, 4)
        return np.concatenate([states[:, parts["eef_pos"]], quat], axis=1)

    def slices(self) -> dict[str, slice]:
        out, i = {}, 0
        for name, n in self.parts:
            out[name] = slice(i, i + n)
            i += n
        return out


ROBOT_OBS = ObsSpec(ROBOT_OBS_PARTS)


@dataclass(frozen=True)
class StepResult:
    """t: control steps since the reset (the time line); clock: those that count against the horizon
    (every step but holds); done: success, or the clock at the horizon."""

    obs: np.ndarray
    success: bool
    done: bool
    t: int
    clock: int


@dataclass(frozen=True)
class TaskGoal:
    """A task's goal as a human operator knows it (what the robot's camera may not show): ``text``,
    one markdown line for the console."""

    text: str


def _make_scene_env(task: Task, horizon: int):
    """Builds the robosuite env for ``task``; imported lazily (robosuite is slow to import)."""
    _quiet_robosuite()
    from robosuite.controllers import load_composite_controller_config
    from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
    from robosuite.models.arenas import TableArena
    from robosuite.models.tasks import ManipulationTask

    class SceneEnv(ManipulationEnv):
        """Table-top Panda scene whose objects and placement come from ``task``."""

        def __init__(self, **kwargs):
            self.task = task
            super().__init__(**kwargs)

        def _load_model(self):
            super()._load_model()
            robot = self.robots[0]
            robot.robot_model.set_base_xpos(robot.robot_model.base_xpos_offset["table"](TABLE_FULL_SIZE[0]))
            arena = TableArena(
                table_full_size=TABLE_FULL_SIZE,
                table_friction=(1.0, 5e-3, 1e-4),
                table_offset=np.array((0.0, 0.0, TABLE_TOP_Z)),
            )
            arena.set_origin([0, 0, 0])
            self.scene_objects = self.task.build_objects()
            self.model = ManipulationTask(
                mujoco_arena=arena,
                mujoco_robots=[robot.robot_model],
                mujoco_objects=list(self.scene_objects.values()),
            )

        def reward(self, action=None):
            return 0.0

        def _check_success(self):
            return False

    config = load_composite_controller_config(robot="Panda")
    arm = config["body_parts"]["right"]
    arm["input_type"] = "absolute"
    arm["input_ref_frame"] = "world"
    return SceneEnv(
        robots="Panda",
        controller_configs=config,
        initialization_noise={"magnitude": task.init_joint_noise, "type": "gaussian"},
        use_camera_obs=False,
        has_renderer=False,
        has_offscreen_renderer=False,
        control_freq=CONTROL_FREQ,
        horizon=horizon,
        ignore_done=True,
        hard_reset=False,
    )


class Task(ABC):
    """One simulated robot doing one task.

    Subclasses define the scene (``build_objects``), the seeded placement
    (``place``), the state-based observation (``observe``), ``check_success`` and the
    privileged state the scripted expert may read (``privileged``).

    A task built for a policy that sees (``sim.registry.make_task(name, images=True)``: ``sees_cameras``)
    observes as the paper's policies do: its frames carry its cameras' images and its observation vector
    (``observation``, ``obs_spec``) is the robot's own state (``ROBOT_OBS``); the state-based one stays
    ``type(task).obs_spec`` for experts, the oracle and tests.
    """

    name: str
    description: str
    problem: str
    horizon: int
    obs_spec: ObsSpec
    action_space: ActionSpace
    object_name: str
    init_joint_noise: float = INIT_JOINT_NOISE  # radians, gaussian, the robot's joints at reset
    # the cameras a policy of this task sees, as the paper's (``sim.cameras.CameraSpec``)
    cameras: tuple[CameraSpec, ...] = ()
    with_images: bool = False  # each frame carries what the policy's cameras see (``RobotFrame.images``)
    _cameras: PolicyCameras | None = None  # built on the first ``images`` call

    def __init__(self) -> None:
        self._env = None
        self._t = 0
        self._clock = 0
        self._seed: int | None = None
        self._gripper = -1.0  # the gripper command in force (our convention: -1 open, +1 closed)

    # -- subclass hooks ---------------------------------------------------
    @abstractmethod
    def build_objects(self) -> dict:
        """Name -> robosuite MujocoObject, created once per model load."""

    @abstractmethod
    def place(self, rng: np.random.Generator) -> None:
        """Sets the seeded initial state of the scene's objects."""

    @abstractmethod
    def observe(self) -> np.ndarray:
        """The state-based observation vector (``type(self).obs_spec.dim``,), float64."""

    @property
    def sees_cameras(self) -> bool:
        """The task observes as a policy that sees cameras does: images and the robot's own state."""
        return self.with_images

    def see_cameras(self) -> None:
        """From now on the task observes as a policy that sees cameras does (``sees_cameras``)."""
        self.with_images = True
        self.obs_spec = ROBOT_OBS

    def observation(self) -> np.ndarray:
        """What the policy observes now (``obs_spec.dim``,): ``observe`` for a state-based policy, the
        robot's own state (``robot_obs``) for one that sees cameras."""
        return self.robot_obs() if self.sees_cameras else self.observe()

    @abstractmethod
    def check_success(self) -> bool: ...

    @abstractmethod
    def privileged(self) -> dict:
        """Ground truth the scripted expert may use (true poses, hidden goals)."""

    def goal(self, scene: dict) -> TaskGoal:
        """The goal for the operator, from ``scene``: what ``privileged`` gave (as a ``RobotFrame``'s
        ``goal``, plain JSON values), so it needs no simulation. By default the task's description."""
        return TaskGoal(self.description)

    def on_step(self) -> None:  # noqa: B027 - optional hook
        """Called after each control step, before observing."""

    def episode_info(self) -> dict:
        """Task-specific outcome details of the current episode (JSON-serialisable)."""
        return {}

    # -- symmetry ---------------------------------------------------------------
    symmetry_order: int = 1  # physically identical poses of the scene that observe differently

    def symmetric_observation(self, obs: np.ndarray, k: np.ndarray) -> np.ndarray:
        """obs (..., dim) as observed with the scene turned into its k-th identical pose,
        k (...) in [0, symmetry_order). The identity for tasks without such a symmetry; training
        uses it to augment demonstrations (``hitl train --symmetry-augment``)."""
        return obs

    # -- environment access -----------------------------------------------
    @property
    def env(self):
        if self._env is None:
            self._env = _make_scene_env(self, self.horizon)
        return self._env

    @property
    def sim(self):
        return self.env.sim

    @property
    def t(self) -> int:
        return self._t

    @property
    def clock(self) -> int:
        """Steps since the reset that count against the horizon (holds do not)."""
        return self._clock

    @property
    def seed(self) -> int | None:
        return self._seed

    def reset(self, seed: int) -> np.ndarray:
        """Seeded reset: the same seed gives the same initial state."""
        env = self.env
        self._seed = int(seed)
        env.rng = np.random.default_rng([self._seed, 0])  # robot joint noise
        env.reset()
        self.place(np.random.default_rng([self._seed, 1]))
        self.sim.forward()
        self._settle()
        self._t = 0
        self._clock = 0
        self._gripper = -1.0
        return self.observation()

    def step(self, action: np.ndarray, hold: bool = False) -> StepResult:
        """Applies an absolute action (10,) for one control step (1 / CONTROL_FREQ s).

        hold: the robot only holds its pose while it waits for an operator; the physics steps, but the
        episode clock (what the horizon counts) does not: waiting for help does not use up the episode.
        The policy's and the operator's steps count, as in the paper."""
        action = self.action_space.validate(action)
        env_action = np.concatenate([action[0:3], rot6d_to_rotvec(action[3:9]), action[9:10]])
        self.env.step(env_action)
        self._gripper = float(action[9])
        self._t += 1
        self._clock += 0 if hold else 1
        self.on_step()
        success = self.check_success()
        return StepResult(self.observation(), success, success or self._clock >= self.horizon, self._t, self._clock)

    def teleop(self, command: TeleopCommand) -> TeleopTarget:
        """Converts an operator command into an absolute action from the current pose."""
        pos, rot = self.ee_pose()
        return self.action_space.apply_teleop(command, pos, rot)

    def hold_action(self) -> np.ndarray:
        """The action that keeps the current pose and gripper state."""
        pos, rot = self.ee_pose()
        return self.action_space.make_action(pos, rot, self.gripper_command())

    def _settle(self, steps: int = 5) -> None:
        """Lets objects come to rest while the arm holds its initial pose."""
        hold = self.hold_action()
        hold[9] = -1.0
        for _ in range(steps):
            self.env.step(np.concatenate([hold[0:3], rot6d_to_rotvec(hold[3:9]), [-1.0]]))
            self.on_step()

    # -- robot state --------------------------------------------------------
    def _ee_site(self) -> int:
        robot = self.env.robots[0]
        return robot.eef_site_id["right"]

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """End-effector (grip site) position (3,) and rotation matrix (3, 3), world frame."""
        sid = self._ee_site()
        return self.sim.data.site_xpos[sid].copy(), self.sim.data.site_xmat[sid].reshape(3, 3).copy()

    def gripper_qpos(self) -> np.ndarray:
        robot = self.env.robots[0]
        return self.sim.data.qpos[robot._ref_gripper_joint_pos_indexes["right"]].copy()

    def mj_model(self):
        """The task's compiled ``mujoco.MjModel`` (built once per task: ``hard_reset`` is off), for viewers that
        pose it from ``joint_positions``. Read-only: copy it before changing anything."""
        return self.sim.model._model

    def mj_data(self):
        """The task's live ``mujoco.MjData``, for reading the scene (``sim.rays``). Read-only."""
        return self.sim.data._data

    def images(self) -> dict[str, np.ndarray]:
        """What the policy's cameras (``cameras``) see now: camera name -> (size, size, 3) uint8 RGB, rendered
        from this task's own simulation state (``sim.cameras.PolicyCameras``)."""
        if not self.cameras:
            return {}
        if self._cameras is None:
            self._cameras = PolicyCameras(self.mj_model(), self.cameras)
        return self._cameras.render(self.mj_data())

    def joint_positions(self) -> np.ndarray:
        """(nq,) the simulation's joint positions: with the task's model and ``placed_poses``, they pose every
        body."""
        return np.array(self.sim.data.qpos, dtype=np.float64)

    def placed_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Model body -> (position, quaternion xyzw) of each body that ``place`` moves by its position in the
        model, not by a joint (a child of the world): ``joint_positions`` does not pose it. None by default."""
        return {}

    def gripper_opening(self) -> float:
        """Finger gap in metres (0.08 fully open)."""
        q = self.gripper_qpos()
        return float(q[0] - q[1])

    def gripper_command(self) -> float:
        """The gripper command in force: the last action's gripper value (-1 open .. +1 closed), open
        (-1) before the episode's first step. Calibration's probe centres hold the recorded command the
        same way (``policy.calibrate.current_actions``). robosuite's own ``current_action`` is not used:
        it is the gripper's rate-limited internal state, with the opposite sign (+1 open, -1 closed)."""
        return self._gripper

    def robot_obs(self) -> np.ndarray:
        """eef_pos (3), eef_rot6d (6), gripper_qpos (2)."""
        pos, rot = self.ee_pose()
        return np.concatenate([pos, mat_to_rot6d(rot), self.gripper_qpos()])

    # -- bodies ---------------------------------------------------------------
    def body_id(self, name: str) -> int:
        return self.sim.model.body_name2id(name)

    def body_pose(self, body_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) and quaternion (x, y, z, w) of a body."""
        return self.sim.data.body_xpos[body_id].copy(), wxyz_to_xyzw(self.sim.data.body_xquat[body_id])

    def set_free_body(self, obj, pos: np.ndarray, quat_xyzw: np.ndarray) -> None:
        quat_wxyz = np.concatenate([quat_xyzw[3:], quat_xyzw[:3]])
        self.sim.data.set_joint_qpos(obj.joints[0], np.concatenate([pos, quat_wxyz]))

    def rest_on_table(self, obj, xy: np.ndarray, quat_xyzw: np.ndarray, clearance: float = 0.001) -> None:
        """Places a free object at ``xy`` with its lowest point just above the table."""
        self.set_free_body(obj, np.array([xy[0], xy[1], TABLE_TOP_Z + 0.5]), quat_xyzw)
        self.sim.forward()
        lowest = self._lowest_point(self.body_id(obj.root_body))
        z = TABLE_TOP_Z + 0.5 + (TABLE_TOP_Z + clearance - lowest)
        self.set_free_body(obj, np.array([xy[0], xy[1], z]), quat_xyzw)

    def _geom_corners(self, root_body: int) -> np.ndarray:
        """(8 * G, 3) world corners of the bounding boxes of a body's (and its children's) G geoms."""
        m, d = self.sim.model, self.sim.data
        bodies = {root_body} | {b for b in range(m.nbody) if m.body_rootid[b] == root_body and b != 0}
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        corners = [
            (m.geom_aabb[g, :3] + signs * m.geom_aabb[g, 3:]) @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
            for g in range(m.ngeom)
            if m.geom_bodyid[g] in bodies
        ]
        return np.concatenate(corners) if corners else np.zeros((0, 3))

    def _lowest_point(self, root_body: int) -> float:
        """Lowest world z over the bounding boxes of a body's (and its children's) geoms."""
        corners = self._geom_corners(root_body)
        return float(corners[:, 2].min()) if len(corners) else np.inf

    def body_extent(self, root_body: int) -> np.ndarray:
        """(3,) size of a body's (and its children's) geometry along the body's own axes (m): the
        oriented bounding box a perception stack would report for a rigid object."""
        corners = self._geom_corners(root_body)
        d = self.sim.data
        local = (corners - d.body_xpos[root_body]) @ d.body_xmat[root_body].reshape(3, 3)
        return local.max(0) - local.min(0)

    @abstractmethod
    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Frame name -> (position, quaternion xyzw) of each object, for playback."""

    def metadata(self) -> dict:
        return {"task": self.name, "object": self.object_name, "horizon": self.horizon}

    def close(self) -> None:
        if self._cameras is not None:
            self._cameras.close()
            self._cameras = None
        if self._env is not None:
            self._env.close()
            self._env = None

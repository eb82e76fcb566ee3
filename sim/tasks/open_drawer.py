"""Open drawer: a cabinet with three drawers side by side; open the intended one.

Action multi-modality: each episode has an intended drawer that the
observation does not reveal. The intended drawer is ``seed % 3``, so
consecutive seeds split evenly across the drawers. Success means the intended
drawer is open by at least ``OPEN_DISTANCE`` (and no other drawer is).

The choice is made in the first steps, and an operator's early steer there must still show when the
policy takes over again: the expert first crosses to the intended drawer's side (``sim.experts.OpenDrawerExpert``),
the cabinet stands within ``CABINET_Y_SPREAD`` of the same place across the table, and the robot's joints
start within ``init_joint_noise`` of its home pose. A few centimetres across then tell the drawers apart;
with the start spread over 6 cm across the cabinet (±4 cm, 0.02 rad), they looked like a start towards
another drawer (docs/benchmarks/hitl.md, "Open-drawer").
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import TABLE_TOP_Z, ObsSpec, Task, TaskGoal
from sim.objects import CabinetGeometry, make_cabinet
from sim.spaces import ActionSpace
from sim.vision import CameraSpec

OPEN_DISTANCE = 0.10  # metres of slide travel
WRONG_DRAWER_TOLERANCE = 0.03  # other drawers may move this much
CABINET = CabinetGeometry()
CABINET_X = 0.10  # nominal cabinet centre, randomised per episode
CABINET_X_SPREAD = 0.03  # metres either way, along x (towards the robot)
CABINET_Y_SPREAD = 0.01  # metres either way, across the table
DRAWER_NAMES = ("right", "middle", "left")  # drawer 0 is at -y: the robot's right

DRAWER_OBS = ObsSpec(
    (
        ("eef_pos", 3),
        ("eef_rot6d", 6),
        ("gripper_qpos", 2),
        ("drawer_opening", CABINET.drawers),
        ("handle_pos", 3 * CABINET.drawers),
    )
)


class OpenDrawerTask(Task):
    name = "open-drawer"
    description = "Open the intended one of three drawers (not in the observation)"
    problem = "action multi-modality"
    horizon = 250
    obs_spec = DRAWER_OBS
    # the paper's drawer policy sees one camera (96 x 96 crops); robosuite's front view faces the robot from
    # across the table and sees the cabinet's back, its side view sees the arm and the drawers' handles
    cameras = (CameraSpec("side", 104, 96),)
    action_space = ActionSpace(pos_low=(-0.25, -0.25, 0.80), pos_high=(0.20, 0.25, 1.15))
    object_name = "cabinet"
    init_joint_noise = 0.005  # radians: the gripper starts within about 0.5 cm of the same place

    def __init__(self, intended: int | None = None) -> None:
        super().__init__()
        if intended is not None and intended not in range(CABINET.drawers):
            raise ValueError(f"intended drawer must be in 0..{CABINET.drawers - 1}, got {intended!r}")
        self._fixed_intended = intended
        self.intended = 0

    def build_objects(self) -> dict:
        self.cabinet = make_cabinet("cabinet")
        return {"cabinet": self.cabinet}

    def place(self, rng: np.random.Generator) -> None:
        m = self.sim.model
        root = self.body_id(self.cabinet.root_body)
        m.body_pos[root] = [
            CABINET_X + rng.uniform(-CABINET_X_SPREAD, CABINET_X_SPREAD),
            rng.uniform(-CABINET_Y_SPREAD, CABINET_Y_SPREAD),
            TABLE_TOP_Z + CABINET.wall,
        ]
        for i in range(CABINET.drawers):
            self.sim.data.set_joint_qpos(self._joint(i), 0.0)
            self.sim.data.set_joint_qvel(self._joint(i), 0.0)
        # An even split over consecutive seeds: demonstrations cover every drawer equally.
        seed = self.seed or 0
        self.intended = seed % CABINET.drawers if self._fixed_intended is None else self._fixed_intended

    def _joint(self, i: int) -> str:
        return f"{self.cabinet.naming_prefix}slide{i}"

    def openings(self) -> np.ndarray:
        return np.array([self.sim.data.get_joint_qpos(self._joint(i)) for i in range(CABINET.drawers)])

    def handle_positions(self) -> np.ndarray:
        """(drawers, 3) handle centres in the world frame."""
        ids = [self.sim.model.site_name2id(f"{self.cabinet.naming_prefix}handle_site{i}") for i in range(3)]
        return self.sim.data.site_xpos[ids].copy()

    def observe(self) -> np.ndarray:
        return np.concatenate([self.robot_obs(), self.openings(), self.handle_positions().ravel()])

    def check_success(self) -> bool:
        opening = self.openings()
        others = np.delete(opening, self.intended)
        return bool(opening[self.intended] >= OPEN_DISTANCE and np.all(others < WRONG_DRAWER_TOLERANCE))

    def episode_info(self) -> dict:
        """``intended`` and ``opened`` drawer (None when no drawer is open past OPEN_DISTANCE)."""
        return {"intended": self.intended, "opened": self.opened_drawer()}

    def opened_drawer(self) -> int | None:
        """Which drawer is open past OPEN_DISTANCE (the most open one), if any."""
        opening = self.openings()
        i = int(np.argmax(opening))
        return i if opening[i] >= OPEN_DISTANCE else None

    def privileged(self) -> dict:
        return {
            "intended": self.intended,
            "handles": self.handle_positions(),
            "openings": self.openings(),
            "pull_axis": np.array([-1.0, 0.0, 0.0]),
            "table_z": TABLE_TOP_Z,
        }

    def goal(self, scene: dict) -> TaskGoal:
        """Which drawer to open: the operator knows it, the robot does not."""
        intended = scene.get("intended")
        if isinstance(intended, int) and 0 <= intended < len(DRAWER_NAMES):
            return TaskGoal(f"Open the **{DRAWER_NAMES[intended]}** drawer (the robot does not know which).")
        return TaskGoal(self.description)

    def metadata(self) -> dict:
        return super().metadata() | {"intended_drawer": self.intended, "intended_name": DRAWER_NAMES[self.intended]}

    def placed_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The cabinet: ``place`` sets its position in the model (it has no joint of its own)."""
        return {self.cabinet.root_body: self.body_pose(self.body_id(self.cabinet.root_body))}

    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        identity = Rotation.identity().as_quat()
        root = self.body_id(self.cabinet.root_body)
        poses = {"cabinet": self.body_pose(root)}
        for i, handle in enumerate(self.handle_positions()):
            poses[f"drawer_{DRAWER_NAMES[i]}"] = (handle, identity)
        return poses

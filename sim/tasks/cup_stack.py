"""Cup stacking: pick the green cup and place it inside the red cup.

Partial observability: once the green cup is carried to within
``OCCLUSION_RADIUS`` (15 cm, horizontal distance) of the red cup, the held cup
and the arm hide the red one, as the held cup hides the bottom cup from the
cameras in the paper's task. While hidden, the red-cup channels read zero and ``red_visible``
reads 0: with an observation history of 1 the policy must align the cups
without seeing the red one, which is where the paper's policy fails. The cups
start at least ``MIN_CUP_SEPARATION`` apart, so the red cup is always visible
at the start of an episode.
"""

from __future__ import annotations

import numpy as np

from sim.env import TABLE_TOP_Z, ObsSpec, Task, TaskGoal
from sim.objects import CupGeometry, make_cup
from sim.rotations import quat_to_rot6d
from sim.spaces import ActionSpace
from sim.vision import CameraSpec

# metres, horizontal distance green cup centre to red cup centre. At 10 cm a policy trained on this
# observation still inserted 4 of 20 cups unassisted (docs/policy.md); at 15 cm the red cup is hidden
# for the whole final approach, whose end the insertion needs.
OCCLUSION_RADIUS = 0.15
MIN_CUP_SEPARATION = 0.18
GREEN = CupGeometry(inner_radius=0.022, outer_radius=0.028, height=0.085)
RED = CupGeometry(inner_radius=0.040, outer_radius=0.047, height=0.045)
GRASPED_LIFT = 0.03  # green cup bottom this far above the table counts as picked up
RELEASED_OPENING = 0.065  # finger gap above which the green cup counts as let go

CUP_OBS = ObsSpec(
    (
        ("eef_pos", 3),
        ("eef_rot6d", 6),
        ("gripper_qpos", 2),
        ("green_pos", 3),
        ("green_rot6d", 6),
        ("red_pos_observed", 3),
        ("green_to_eef_pos", 3),
        ("red_observed_to_green_pos", 3),
        ("red_visible", 1),
    )
)


class CupStackTask(Task):
    name = "cup-stack"
    description = "Pick the green cup and place it inside the red cup"
    problem = "partial observability"
    horizon = 400
    obs_spec = CUP_OBS
    cameras = (CameraSpec("side", 104, 96), CameraSpec("wrist", 104, 96), CameraSpec("front", 104, 96))  # the paper's
    action_space = ActionSpace(pos_low=(-0.25, -0.25, 0.80), pos_high=(0.20, 0.25, 1.15))
    object_name = "cups"

    def build_objects(self) -> dict:
        self.green = make_cup("green_cup", GREEN, (0.15, 0.7, 0.2, 1.0), density=300)
        self.red = make_cup("red_cup", RED, (0.8, 0.15, 0.12, 1.0), density=3000)
        return {"green_cup": self.green, "red_cup": self.red}

    def place(self, rng: np.random.Generator) -> None:
        while True:
            green = rng.uniform((-0.10, -0.18), (0.10, 0.18))
            red = rng.uniform((-0.10, -0.18), (0.10, 0.18))
            if np.linalg.norm(green - red) >= MIN_CUP_SEPARATION:
                break
        upright = np.array([0.0, 0.0, 0.0, 1.0])
        self.rest_on_table(self.green, green, upright)
        self.rest_on_table(self.red, red, upright)

    @property
    def _green_body(self) -> int:
        return self.body_id(self.green.root_body)

    @property
    def _red_body(self) -> int:
        return self.body_id(self.red.root_body)

    def reset(self, seed: int) -> np.ndarray:
        self._grasped = False
        return super().reset(seed)

    def on_step(self) -> None:
        green = self.sim.data.body_xpos[self._green_body]
        if green[2] - GREEN.half_height > TABLE_TOP_Z + GRASPED_LIFT:
            self._grasped = True

    def episode_info(self) -> dict:
        """``grasped``: the green cup was lifted off the table; ``inserted``: it is inside the red cup."""
        return {"grasped": bool(getattr(self, "_grasped", False)), "inserted": self._green_inside()}

    def _red_visible(self) -> bool:
        green = self.sim.data.body_xpos[self._green_body]
        red = self.sim.data.body_xpos[self._red_body]
        return float(np.linalg.norm(green[:2] - red[:2])) >= OCCLUSION_RADIUS

    def observe(self) -> np.ndarray:
        eef = self.robot_obs()
        green_pos, green_quat = self.body_pose(self._green_body)
        visible = self._red_visible()
        red = self.sim.data.body_xpos[self._red_body].copy() if visible else np.zeros(3)
        to_red = red - green_pos if visible else np.zeros(3)
        return np.concatenate(
            [eef, green_pos, quat_to_rot6d(green_quat), red, green_pos - eef[0:3], to_red, [float(visible)]]
        )

    def _green_inside(self) -> bool:
        green = self.sim.data.body_xpos[self._green_body]
        red = self.sim.data.body_xpos[self._red_body]
        centred = np.linalg.norm(green[:2] - red[:2]) < RED.inner_radius - GREEN.outer_radius + 0.006
        green_bottom = green[2] - GREEN.half_height
        red_rim = red[2] + RED.half_height
        return bool(centred and green_bottom < red_rim - 0.02)

    def check_success(self) -> bool:
        return self._green_inside() and self.gripper_opening() > RELEASED_OPENING

    def privileged(self) -> dict:
        green = self.sim.data.body_xpos[self._green_body].copy()
        red = self.sim.data.body_xpos[self._red_body].copy()
        return {
            "green_pos": green,
            "red_pos": red,
            "green_grasp_point": green + [0, 0, GREEN.half_height - 0.025],
            "green_bottom_z": green[2] - GREEN.half_height,
            "red_floor_z": red[2] - RED.half_height + RED.bottom,
            "red_rim_z": red[2] + RED.half_height,
            "red_visible": self._red_visible(),
            "table_z": TABLE_TOP_Z,
        }

    def goal(self, scene: dict) -> TaskGoal:
        """The description, and whether the red cup is hidden from the robot's camera."""
        if "red_visible" not in scene:
            return TaskGoal(self.description)
        seen = "" if scene["red_visible"] else " The red cup is hidden from the robot's camera."
        return TaskGoal(f"{self.description}.{seen}")

    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {"green_cup": self.body_pose(self._green_body), "red_cup": self.body_pose(self._red_body)}

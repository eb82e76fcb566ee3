"""Lift: pick an object up off the table.

``lift-cube`` is the training distribution. ``lift-nut``, ``lift-hammer`` and
``lift-hook`` put robosuite's RoundNut, Hammer and HookFrame in place of the
cube (distribution shift): the observation layout is identical, so a policy
trained on the cube runs on them unchanged.

The observation carries the object's geometry the way a perception stack
would: ``object_extent`` is the size of its oriented bounding box along the
object's own axes (the axes ``object_rot6d`` gives), with a few millimetres of
estimation error drawn afresh at every step (seeded by the episode's seed and
the step), so it is noise to the policy rather than a per-episode constant that
tells the training episodes apart. A cube-trained policy therefore sees an
unseen object as new in its input, as the paper's camera-based policy does
(see docs/policy.md, "What the policies see").

``finger_rays`` is the local view the paper's wrist camera gives: range rays cast from the fingers across
the gap and down (``sim.rays``). The box says roughly where an object is; the rays say whether the
fingers are around something, which is what closing needs, for any object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import TABLE_TOP_Z, ObsSpec, Task, TaskGoal
from sim.rays import RAYS, FingerRays
from sim.rotations import quat_to_rot6d
from sim.spaces import ActionSpace
from sim.vision import CameraSpec

LIFT_HEIGHT = 0.04  # success: the object's root is this much above where it rested
EXTENT_NOISE = 0.002  # m, std of the perceived bounding box's error per axis and step
LIFT_WORKSPACE = ActionSpace(pos_low=(-0.25, -0.25, 0.80), pos_high=(0.20, 0.25, 1.15))
LIFT_OBS = ObsSpec(
    (
        ("eef_pos", 3),
        ("eef_rot6d", 6),
        ("gripper_qpos", 2),
        ("object_pos", 3),
        ("object_rot6d", 6),
        ("object_to_eef_pos", 3),
        ("object_extent", 3),
        ("finger_rays", RAYS),
    )
)


@dataclass(frozen=True)
class GraspSpec:
    """Where the expert grasps an object, in the object's frame.

    point: grasp point (3,); bar_axis: the local axis of the grasped bar, which
    the gripper's x axis is aligned with so the fingers close across it;
    symmetry: the bar's yaw symmetry (pi for a bar, pi/2 for a cube face).
    """

    point: tuple[float, float, float]
    bar_axis: tuple[float, float, float]
    symmetry: float = np.pi
    grasp_depth: float = 0.0  # extra descent below the grasp point (m)


def _make_cube(name: str):
    from robosuite.models.objects import BoxObject

    return BoxObject(name=name, size=[0.021, 0.021, 0.021], rgba=[0.85, 0.1, 0.1, 1.0])


def _make_nut(name: str):
    from robosuite.models.objects import RoundNutObject

    return RoundNutObject(name=name)


def _make_hammer(name: str):
    from robosuite.models.objects import HammerObject

    return HammerObject(
        name=name,
        handle_length=(0.16, 0.16),
        handle_radius=(0.014, 0.014),
        handle_density=(150, 150),
        rng=np.random.default_rng(0),
    )


def _make_hook(name: str):
    from robosuite.models.objects.composite import HookFrame

    return HookFrame(name=name, frame_length=0.16, frame_height=0.12, frame_thickness=0.022, density=250)


@dataclass(frozen=True)
class LiftObject:
    key: str
    factory: object
    grasp: GraspSpec
    default_quat: tuple[float, float, float, float] | None = None  # before the random yaw
    # yaw about the object's vertical axis through its body origin that leaves it unchanged
    # (the cube: a quarter turn); None for objects with no such symmetry
    body_symmetry: float | None = None


LIFT_OBJECTS: dict[str, LiftObject] = {
    "cube": LiftObject(
        "cube",
        _make_cube,
        GraspSpec((0, 0, 0), (1, 0, 0), symmetry=np.pi / 2),
        body_symmetry=np.pi / 2,
    ),
    "nut": LiftObject("nut", _make_nut, GraspSpec((0.06, 0, 0), (1, 0, 0))),
    "hammer": LiftObject("hammer", _make_hammer, GraspSpec((0, 0, 0.02), (0, 0, 1))),
    "hook": LiftObject("hook", _make_hook, GraspSpec((0.03, 0, 0.049), (1, 0, 0))),
}


class LiftTask(Task):
    problem = "distribution shift"
    horizon = 150
    obs_spec = LIFT_OBS
    cameras = (CameraSpec("front", 84, 76), CameraSpec("wrist", 84, 76))  # the paper's Lift-sim: 76 x 76 crops
    action_space = LIFT_WORKSPACE

    def __init__(self, object_key: str) -> None:
        super().__init__()
        if object_key not in LIFT_OBJECTS:
            raise ValueError(f"unknown lift object {object_key!r}; known: {sorted(LIFT_OBJECTS)}")
        self.spec = LIFT_OBJECTS[object_key]
        self.object_name = object_key
        self.name = f"lift-{object_key}"
        self.description = f"Lift the {object_key} {LIFT_HEIGHT * 100:.0f} cm off the table"
        if object_key == "cube":
            self.problem = "training distribution"
        self._rest_z = 0.0
        self._max_lift = 0.0
        self._first_close: tuple[int, float, float] | None = None
        self._rays: FingerRays | None = None  # built on the first observation, for the task's model
        sym = self.spec.body_symmetry
        self.symmetry_order = round(2 * np.pi / sym) if sym else 1

    def symmetric_observation(self, obs: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Turns the observed object orientation by k * body_symmetry about the vertical: the
        object looks the same, its position and the gripper do not move."""
        if self.symmetry_order == 1:
            return obs
        angle = np.asarray(k) * self.spec.body_symmetry
        c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
        out = np.array(obs, copy=True)
        rot6d = self.obs_spec.slices()["object_rot6d"]
        for col in (slice(rot6d.start, rot6d.start + 3), slice(rot6d.start + 3, rot6d.stop)):
            x, y = obs[..., col][..., 0:1], obs[..., col][..., 1:2]
            out[..., col.start : col.start + 2] = np.concatenate([c * x - s * y, s * x + c * y], axis=-1)
        return out

    def build_objects(self) -> dict:
        self.obj = self.spec.factory(self.object_name)
        return {self.object_name: self.obj}

    def _base_quat(self) -> np.ndarray:
        if self.spec.default_quat is not None:
            return np.asarray(self.spec.default_quat, float)
        init = getattr(self.obj, "init_quat", None)
        return np.asarray(init if init is not None else (0, 0, 0, 1), float)

    def place(self, rng: np.random.Generator) -> None:
        xy = np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.12, 0.12)])
        yaw = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi))
        quat = (yaw * Rotation.from_quat(self._base_quat())).as_quat()
        self.rest_on_table(self.obj, xy, quat)

    def _settle(self, steps: int = 5) -> None:
        super()._settle(steps)
        self._rest_z = float(self.sim.data.body_xpos[self._body][2])
        self._max_lift = 0.0
        self._first_close = None
        self._extent = self.body_extent(self._body)  # rigid: measured once per episode

    def perceived_extent(self) -> np.ndarray:
        """(3,) the bounding box as perceived at this step: the true one plus seeded noise."""
        return self._extent + np.random.default_rng([self.seed or 0, 2, self.t]).normal(0.0, EXTENT_NOISE, 3)

    def on_step(self) -> None:
        self._max_lift = max(self._max_lift, float(self.sim.data.body_xpos[self._body][2]) - self._rest_z)
        if self._first_close is None and self._gripper > 0:
            eef, goal = self.ee_pose()[0], self.privileged()
            in_plane = [float(np.linalg.norm((eef - goal[k])[:2])) for k in ("grasp_point", "object_pos")]
            self._first_close = (self.t - 1, *in_plane)  # the 0-based index of the closing step

    def episode_info(self) -> dict:
        """``max_lift``: the highest the object got above its resting height (m). Where the gripper was
        first told to close: ``first_close_step`` (0-based), and the end effector's distance in the plane
        from the object's grasp point (``first_close_to_grasp_m``) and from its body origin
        (``first_close_to_origin_m``); None when it never closed. A policy that grasps an unseen object
        where it would grasp a cube closes near the origin, away from the grasp point."""
        step, to_grasp, to_origin = self._first_close or (None, None, None)
        return {
            "max_lift": round(self._max_lift, 4),
            "first_close_step": step,
            "first_close_to_grasp_m": None if to_grasp is None else round(to_grasp, 4),
            "first_close_to_origin_m": None if to_origin is None else round(to_origin, 4),
        }

    @property
    def _body(self) -> int:
        return self.body_id(self.obj.root_body)

    def finger_rays(self) -> np.ndarray:
        """(RAYS,) the finger range rays at this step (``sim.rays``)."""
        model = self.mj_model()
        if self._rays is None or self._rays.model is not model:
            self._rays = FingerRays(model)
        return self._rays.read(self.mj_data())

    def observe(self) -> np.ndarray:
        pos, quat = self.body_pose(self._body)
        eef = self.robot_obs()
        return np.concatenate(
            [eef, pos, quat_to_rot6d(quat), pos - eef[0:3], self.perceived_extent(), self.finger_rays()]
        )

    def check_success(self) -> bool:
        return bool(self.sim.data.body_xpos[self._body][2] > self._rest_z + LIFT_HEIGHT)

    def privileged(self) -> dict:
        pos, quat = self.body_pose(self._body)
        rot = Rotation.from_quat(quat)
        grasp_point = pos + rot.apply(self.spec.grasp.point)
        bar = rot.apply(self.spec.grasp.bar_axis)
        return {
            "object_pos": pos,
            "grasp_point": grasp_point,
            "grasp_yaw": float(np.arctan2(bar[1], bar[0])),
            "yaw_symmetry": self.spec.grasp.symmetry,
            "grasp_depth": self.spec.grasp.grasp_depth,
            "rest_z": self._rest_z,
            "table_z": TABLE_TOP_Z,
        }

    def goal(self, scene: dict) -> TaskGoal:
        """The description and the yaw of the bar to grasp across (the object's own, in the world)."""
        if "grasp_yaw" not in scene:
            return TaskGoal(self.description)
        yaw = math.degrees(float(scene["grasp_yaw"]))
        return TaskGoal(f"{self.description}; grasp across its bar (yaw {yaw:.0f}°).")

    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {self.object_name: self.body_pose(self._body)}

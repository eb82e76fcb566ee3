"""Finger range rays: what lies between and under a Panda gripper's fingers, the local cue a wrist camera gives.

A policy that sees an object only through a global pose and bounding box cannot tell, at an unseen object,
whether its fingers are around something. The paper's wrist camera can, and there the lift "happens without
intervention" once the gripper is placed. A few rays cast with ``mujoco.mj_ray`` from the fingers cost far
less than a rendered wrist depth image and carry the part of that image the grasp needs.

``FingerRays.read`` returns ``RAYS`` distances in metres, in this order:

- ``across`` (3): from the left finger's pad towards the right pad, at the pad's centre and ``ACROSS_OFFSET``
  to either side of it along the fingers' width (the grip site's y axis, which a grasped bar lies along):
  the distance to the first thing between the pads, capped at the pads' distance (nothing between: the gap);
- ``down`` (3): along the grip site's z axis (down, for a gripper pointing down) from the grip site and from
  each pad: the distance to the first thing under it, capped at ``DOWN_RANGE``.

Rays see collision geometry only (geom group 0: the table, objects, fixtures), and pass through the gripper's
own geometry. A ray starting inside a geom does not see that geom (``mj_ray``'s rule): the grip site's down ray
inside a held cube reads the table below it. The readings are exact; what they carry is geometric, the same for
every object, so a cube-trained policy sees an unseen object's bar between its fingers as it saw the cube's.
"""

from __future__ import annotations

import mujoco
import numpy as np

RAYS = 6
LABELS = ("across_centre", "across_plus", "across_minus", "down_site", "down_left", "down_right")
ACROSS_OFFSET = 0.008  # m, the side rays' offset from the pad's centre along the fingers' width
DOWN_RANGE = 0.12  # m, the down rays' cap
GRIP_SITE = "gripper0_right_grip_site"
GRIPPER_ROOT = "gripper0_right_right_gripper"  # the hand; its subtree is the gripper
PADS = ("gripper0_right_finger_joint1_tip", "gripper0_right_finger_joint2_tip")  # left, right
_COLLISION = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # geom group 0 only
_THROUGH = 4  # gripper geoms a ray may pass through before it gives up (there are 6)
_NUDGE = 1e-4  # m past a gripper geom's surface before casting again


class FingerRays:
    """The rays of one compiled model (``mujoco.MjModel``), read against its ``MjData``."""

    def __init__(self, model: mujoco.MjModel) -> None:
        def body(name: str) -> int:
            i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            if i < 0:
                raise ValueError(f"finger rays need body {name!r}; the model has none (not a Panda gripper?)")
            return i

        self.model = model
        self.site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, GRIP_SITE)
        if self.site < 0:
            raise ValueError(f"finger rays need site {GRIP_SITE!r}; the model has none")
        root = body(GRIPPER_ROOT)
        self.pads = tuple(body(n) for n in PADS)
        self.gripper = np.zeros(model.nbody, dtype=bool)
        for b in range(model.nbody):
            a = b
            while a > 0 and a != root:
                a = int(model.body_parentid[a])
            self.gripper[b] = a == root
        self._geom = np.zeros(1, dtype=np.int32)

    def _cast(self, data: mujoco.MjData, start: np.ndarray, direction: np.ndarray, cap: float) -> float:
        """The distance along the unit ``direction`` to the first non-gripper collision geom, at most ``cap``."""
        travelled, point = 0.0, np.array(start, dtype=np.float64)
        for _ in range(_THROUGH + 1):
            dist = mujoco.mj_ray(self.model, data, point, direction, _COLLISION, 1, -1, self._geom)
            if dist < 0 or travelled + dist >= cap:
                return cap
            if not self.gripper[self.model.geom_bodyid[self._geom[0]]]:
                return travelled + dist
            step = dist + _NUDGE
            travelled, point = travelled + step, point + direction * step
        return cap

    def read(self, data: mujoco.MjData) -> np.ndarray:
        """(RAYS,) distances in metres, in ``LABELS`` order."""
        rot = data.site_xmat[self.site].reshape(3, 3)
        left, right = data.xpos[self.pads[0]], data.xpos[self.pads[1]]
        across = right - left
        gap = float(np.linalg.norm(across))
        out = np.empty(RAYS)
        unit = across / gap if gap > 0 else rot[:, 0]
        for i, offset in enumerate((0.0, ACROSS_OFFSET, -ACROSS_OFFSET)):
            out[i] = self._cast(data, left + rot[:, 1] * offset, unit, gap)
        down = np.ascontiguousarray(rot[:, 2])
        for i, start in enumerate((data.site_xpos[self.site], left, right)):
            out[3 + i] = self._cast(data, start, down, DOWN_RANGE)
        return out

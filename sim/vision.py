"""What a policy sees: the cameras a task declares (``CameraSpec``), rendered from the robot's own state.

A task declares the cameras its policy sees and their size (``Task.cameras``; the paper's sets: front and
wrist on lift, side, wrist and front on cup stacking, front on the drawer). ``PolicyCameras`` renders them
from the robot's own ``MjData`` after each control step, on a copy of the task's model drawn cheaply
(``fast_model``): no multisampling, no reflections, and the robot (arm, gripper, mount) drawn from its
collision geoms, each coloured like its body's visual geoms, while the objects and the table keep their
visual geoms. Software OpenGL's cost is geometry, not pixels, and the robot's visual meshes are most of
the scene's vertices (``hitl bench cameras`` measures both ways; docs/policy.md shows what the policy sees).

MuJoCo needs an OpenGL context: ``sim.env`` chooses OSMesa (``MUJOCO_GL=osmesa``, package ``libosmesa6``)
unless the environment says otherwise, before ``mujoco`` is first imported.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

# every camera a policy may see: our name -> robosuite's (the paper's front, side and wrist views)
POLICY_CAMERAS = {"front": "agentview", "side": "sideview", "wrist": "robot0_eye_in_hand"}
COLLISION_GROUP, VISUAL_GROUP = 0, 1  # robosuite's geom groups (target markers are in 2)
HIDDEN_GROUP = 5  # where ``fast_model`` moves the geoms it does not draw
ROBOT_PREFIXES = ("robot0_", "gripper0_", "mount0_", "fixed_mount0_")  # the robot's bodies, its gripper's, mount's


@dataclass(frozen=True)
class CameraSpec:
    """One camera a policy sees: ``name`` (``POLICY_CAMERAS``), rendered ``size`` x ``size`` pixels, of which
    the policy sees a ``crop`` x ``crop`` window (random in training, centred at evaluation)."""

    name: str
    size: int = 84
    crop: int = 76

    def __post_init__(self) -> None:
        if self.name not in POLICY_CAMERAS:
            raise ValueError(f"unknown camera {self.name!r}; cameras: {', '.join(POLICY_CAMERAS)}")
        if not (16 <= self.crop <= self.size <= 512):
            raise ValueError(f"camera {self.name!r}: need 16 <= crop <= size <= 512, got {self.crop}, {self.size}")

    def to_json(self) -> dict:
        return {"name": self.name, "size": self.size, "crop": self.crop}

    @classmethod
    def from_json(cls, d: dict) -> CameraSpec:
        return cls(str(d["name"]), int(d["size"]), int(d["crop"]))


def fast_model(model):
    """A copy of ``model`` drawn cheaply (see the module): no multisampling; the robot's visual geoms hidden
    and its collision geoms shown in their body's colour; the objects' and the arena's visual geoms as they
    are. Only drawing attributes change, so it renders any ``MjData`` of ``model``."""
    import mujoco

    m = copy.deepcopy(model)
    m.vis.quality.offsamples = 0
    body = mujoco.mjtObj.mjOBJ_BODY
    robot = np.array([(mujoco.mj_id2name(m, body, b) or "").startswith(ROBOT_PREFIXES) for b in range(m.nbody)])
    colour = {}  # body -> the colour of its first visual geom
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if m.geom_group[g] == VISUAL_GROUP and b not in colour:
            colour[b] = _visual_colour(m, g)
    for g in range(m.ngeom):
        b, group = int(m.geom_bodyid[g]), m.geom_group[g]
        if robot[b] and group == COLLISION_GROUP:  # drawn, in its body's colour
            m.geom_group[g], m.geom_matid[g] = VISUAL_GROUP, -1
            m.geom_rgba[g] = colour.get(b, m.geom_rgba[g])
        elif (robot[b] and group == VISUAL_GROUP) or group == COLLISION_GROUP:  # the robot's meshes, others' collision
            m.geom_group[g] = HIDDEN_GROUP
    return m


def _visual_colour(m, g: int) -> np.ndarray:
    """(4,) what a geom looks like on average: its material's colour times its texture's mean, or its own."""
    mat = int(m.geom_matid[g])
    if mat < 0:
        return np.array(m.geom_rgba[g], dtype=np.float32)
    rgba = np.array(m.mat_rgba[mat], dtype=np.float32)
    tex = int(m.mat_texid[mat][1])  # mjTEXROLE_RGB
    if tex >= 0:
        adr, n = int(m.tex_adr[tex]), int(m.tex_width[tex] * m.tex_height[tex] * m.tex_nchannel[tex])
        pixels = np.asarray(m.tex_data[adr : adr + n], dtype=np.float32).reshape(-1, int(m.tex_nchannel[tex]))
        rgba[:3] *= pixels[:, :3].mean(0) / 255.0
    return rgba


class PolicyCameras:
    """A task's policy cameras: ``render(data)`` -> camera name -> (size, size, 3) uint8 RGB of that state.
    ``fast``: drawn as served (``fast_model``, no reflections); False: with MuJoCo's defaults (the visual
    meshes, multisampling, reflections), what ``hitl bench cameras`` compares against."""

    def __init__(self, model, specs: tuple[CameraSpec, ...], fast: bool = True) -> None:
        import mujoco

        self.specs = tuple(specs)
        self.model = fast_model(model) if fast else copy.deepcopy(model)
        camera = mujoco.mjtObj.mjOBJ_CAMERA
        missing = [s.name for s in self.specs if mujoco.mj_name2id(self.model, camera, POLICY_CAMERAS[s.name]) < 0]
        if missing:
            raise ValueError(f"the task's model has no camera {', '.join(missing)}")
        biggest = max((s.size for s in self.specs), default=1)
        self.model.vis.global_.offwidth = max(int(self.model.vis.global_.offwidth), biggest)
        self.model.vis.global_.offheight = max(int(self.model.vis.global_.offheight), biggest)
        self.option = mujoco.MjvOption()
        self.option.geomgroup[:] = 0
        self.option.geomgroup[VISUAL_GROUP] = 1
        self._renderers = {size: mujoco.Renderer(self.model, size, size) for size in {s.size for s in self.specs}}
        for r in self._renderers.values() if fast else ():
            r.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0  # the scene keeps its flags across renders

    def render(self, data) -> dict[str, np.ndarray]:
        """The policy's views of ``data`` (the robot's own ``MjData``, as it stands after its step)."""
        out = {}
        for spec in self.specs:
            renderer = self._renderers[spec.size]
            renderer.update_scene(data, camera=POLICY_CAMERAS[spec.name], scene_option=self.option)
            out[spec.name] = renderer.render().copy()
        return out

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()

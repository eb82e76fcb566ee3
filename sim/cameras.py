"""What a robot's cameras show its operator: MuJoCo renders a task's cameras from a state's joint positions.

(The policy's own cameras are ``sim.vision``'s.)

An operator of a real robot works from its camera feeds; the console shows the viewed robot's front and
wrist cameras (``server.cameras``). A ``CameraRig`` holds its own copy of a task's model and data and
renders from a frame's ``qpos`` and placed bodies (``sim.frame.pose_model``): kinematics, no physics step, so the
robot's own simulation is never touched and any process holding the frames can render them.

MuJoCo needs an OpenGL context: on a machine without a display, OSMesa (``MUJOCO_GL=osmesa``, package
``libosmesa6``), chosen before ``mujoco`` is first imported; ``server.camera_worker`` sets it for its
own process.
"""

from __future__ import annotations

import copy

import numpy as np

from sim.frame import pose_model

CAMERAS = {"front": "agentview", "wrist": "robot0_eye_in_hand"}  # the console's: our name -> robosuite's camera
DEFAULT_SIZE = (160, 120)  # width, height
VISUAL_GROUP = 1  # robosuite puts visual geoms in group 1, collision geoms in 0, target markers in 2


class CameraRig:
    """One task's cameras at one size. ``render(qpos, placed)`` -> our camera name -> (H, W, 3) uint8 RGB."""

    def __init__(self, model, width: int = DEFAULT_SIZE[0], height: int = DEFAULT_SIZE[1]) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model = copy.deepcopy(model)
        camera = mujoco.mjtObj.mjOBJ_CAMERA
        missing = [cam for cam in CAMERAS.values() if mujoco.mj_name2id(self.model, camera, cam) < 0]
        if missing:
            raise ValueError(f"the model has no camera {', '.join(missing)}")
        self.model.vis.global_.offwidth = max(int(self.model.vis.global_.offwidth), width)
        self.model.vis.global_.offheight = max(int(self.model.vis.global_.offheight), height)
        self.data = mujoco.MjData(self.model)
        self.option = mujoco.MjvOption()
        self.option.geomgroup[:] = 0
        self.option.geomgroup[VISUAL_GROUP] = 1  # robosuite's visual geoms: not its collision geoms, not its markers
        self.renderer = mujoco.Renderer(self.model, height, width)

    def render(self, qpos: np.ndarray, placed: dict | None = None) -> dict[str, np.ndarray]:
        """The views of the state a frame shows: its ``qpos`` and ``placed`` bodies (``sim.frame.pose_model``)."""
        mujoco = self._mujoco
        pose_model(self.model, self.data, qpos, placed or {})
        mujoco.mj_camlight(self.model, self.data)
        out = {}
        for name, cam in CAMERAS.items():
            self.renderer.update_scene(self.data, camera=cam, scene_option=self.option)
            out[name] = self.renderer.render().copy()
        return out

    def close(self) -> None:
        self.renderer.close()

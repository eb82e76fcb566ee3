"""One browser's 3D view of one robot: the MuJoCo scene, the end-effector frame, the probe ball, the
denoising vector field coloured by GMM mode with the mode means drawn bold, and the target gizmo.

Scene paths follow ``/robots/{id}/...``. Every browser gets its own copy of the task's model (mjviser
changes a model's visual settings when it builds a scene) with robosuite's collision geoms hidden,
and camera tracking off (it would shift the scene under the world-frame overlays).
"""

from __future__ import annotations

import copy
import threading
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np
import viser
from mjviser import ViserMujocoScene
from scipy.spatial.transform import Rotation

from policy.uncertainty import UncertaintyConfig, UncertaintyResult
from sim.frame import RobotFrame, pose_model
from sim.registry import make_task
from web.viser_internals import hide_model_groups, move_fixed_body

# contrasting mode colours (Okabe-Ito, colour-blind safe), in the order of the GMM's modes
MODE_COLORS = np.array(
    [(0, 114, 178), (230, 159, 0), (0, 158, 115), (204, 121, 167), (213, 94, 0), (86, 180, 233), (240, 228, 66)],
    dtype=np.uint8,
)
PROBE_COLOR = (90, 140, 255)
FIELD_LONGEST_M = 0.03  # the longest field arrow; the others keep their lengths relative to it
MODE_LENGTH_M = 0.06  # a mode mean's arrow, at the mode's share of the samples
FIELD_STYLE = {"shaft_radius": 0.0006, "head_radius": 0.0016, "head_length": 0.004}  # m
MODE_STYLE = {"shaft_radius": 0.0025, "head_radius": 0.006, "head_length": 0.012}  # m: the mode means, bold
CAMERA_POSITION = (1.25, 0.95, 1.55)
CAMERA_LOOK_AT = (-0.05, 0.0, 0.9)


class SceneModels:
    """Each task's MuJoCo model, built once (about 1.5 s, on the first browser that shows the task)."""

    def __init__(self, make: Callable = make_task) -> None:
        self._make = make
        self._models: dict[str, mujoco.MjModel] = {}
        self._lock = threading.Lock()

    def copy(self, task: str) -> mujoco.MjModel:
        """A browser's own copy of ``task``'s model."""
        with self._lock:
            if task not in self._models:
                t = self._make(task)
                try:
                    self._models[task] = copy.deepcopy(t.mj_model())
                finally:
                    t.close()
            return copy.deepcopy(self._models[task])


def mode_colors(labels: np.ndarray) -> np.ndarray:
    """(S,) mode labels -> (S, 3) uint8 colours."""
    return MODE_COLORS[np.asarray(labels, dtype=int) % len(MODE_COLORS)]


@dataclass(frozen=True)
class FieldArrows:
    """A denoising field as arrows relative to the probe centre. field: (S, 2, 3) start/end, m; colors:
    (S, 3); modes: (n, 2, 3) each mode's mean direction from its samples' centroid; mode_colors: (n, 3)."""

    field: np.ndarray
    colors: np.ndarray
    modes: np.ndarray
    mode_colors: np.ndarray


def field_arrows(result: UncertaintyResult, normalizer, centre: np.ndarray) -> FieldArrows:
    """Arrows for ``result`` in world units around ``centre`` (3,): each probe sample's denoising direction,
    scaled so the longest is ``FIELD_LONGEST_M``; each mode's mean direction, bold, from its samples'
    centroid, ``MODE_LENGTH_M`` long at a share of 1."""
    world = result.to_world(normalizer)
    start = world.samples - centre
    scale = world.arrow_scale(FIELD_LONGEST_M)
    field = np.stack([start, start + world.vectors * scale], axis=1)
    modes, colors = [], []
    for k in range(result.n):
        mask = world.labels == k
        if not mask.any():
            continue
        direction = world.means[k]
        norm = float(np.linalg.norm(direction))
        if norm == 0:
            continue
        origin = start[mask].mean(axis=0)
        share = float(result.weights[k])
        modes.append([origin, origin + direction / norm * MODE_LENGTH_M * max(share, 0.25)])
        colors.append(MODE_COLORS[k % len(MODE_COLORS)])
    return FieldArrows(
        field.astype(np.float32),
        mode_colors(world.labels),
        np.asarray(modes, np.float32).reshape(-1, 2, 3),
        np.asarray(colors, np.uint8).reshape(-1, 3),
    )


def probe_radii(normalizer, radius: float = UncertaintyConfig.radius) -> np.ndarray:
    """(3,) the probe ball's semi-axes in metres: radius r in the normalized action space, per world axis."""
    return radius * normalizer.span[:3].numpy().astype(np.float64)


def probe_radius(view) -> float:
    """The probe radius r of the robot's denoising signal (the paper's default when it runs none)."""
    signal = view.slot.controller.signals.get("denoising")
    return float(getattr(getattr(signal, "config", None), "radius", UncertaintyConfig.radius))


def wxyz(quat_xyzw: np.ndarray) -> np.ndarray:
    q = np.asarray(quat_xyzw, dtype=np.float64)
    return np.array([q[3], q[0], q[1], q[2]])


class RobotScene:
    """The scene of one robot in one browser (built in about 2-3 s: call it off the event loop)."""

    def __init__(
        self,
        client: viser.ClientHandle,
        robot_id: int,
        model: mujoco.MjModel,
        normalizer,
        version: int,
        radius: float = UncertaintyConfig.radius,
    ) -> None:
        """normalizer: the action normalizer of policy ``version`` (the field's units); radius: the probe's r."""
        self.client, self.robot_id, self.normalizer, self.version = client, robot_id, normalizer, version
        hide_model_groups(model)
        self.model, self.data = model, mujoco.MjData(model)
        self.mj = ViserMujocoScene(client, model, num_envs=1)
        self.mj.camera_tracking_enabled = False
        prefix = f"/robots/{robot_id}"
        scene = client.scene
        self.ee = scene.add_frame(f"{prefix}/ee", axes_length=0.07, axes_radius=0.003, origin_radius=0.006)
        self.probe = scene.add_icosphere(
            f"{prefix}/probe",
            radius=1.0,
            color=PROBE_COLOR,
            opacity=0.18,
            scale=tuple(probe_radii(normalizer, radius)),
            cast_shadow=False,
            receive_shadow=False,
        )
        self.field_root = scene.add_frame(f"{prefix}/field", show_axes=False)
        self.field = scene.add_arrows(
            f"{prefix}/field/samples",
            np.zeros((1, 2, 3)),
            np.zeros((1, 3), np.uint8),
            **FIELD_STYLE,
            visible=False,
        )
        self.modes: viser.ArrowsHandle | None = None
        self.target: viser.TransformControlsHandle | None = None
        self._frame: RobotFrame | None = None
        self._result: UncertaintyResult | None = None
        self._placed: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # the placed bodies' poses the view shows

    def update(self, frame: RobotFrame | None, result: UncertaintyResult | None) -> None:
        """Sends what changed since the last call (the caller wraps a tick in ``client.atomic()``)."""
        if frame is not None and frame is not self._frame:
            self._frame = frame
            if frame.qpos is not None and len(frame.qpos) == self.model.nq:
                pose_model(self.model, self.data, frame.qpos, frame.placed)
                self.mj.update_from_mjdata(self.data)
                self._move_placed(frame.placed)
            self.ee.position, self.ee.wxyz = frame.pos, wxyz(frame.quat)
            self.probe.position = frame.pos
            self.field_root.position = frame.pos
        if result is not self._result and frame is not None:
            self._result = result
            self._draw_field(result, frame.pos)

    def _move_placed(self, placed: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Moves the bodies the task places without a joint (the drawer's cabinet) where they moved since."""
        for name, (pos, quat) in placed.items():
            seen = self._placed.get(name)
            if seen is not None and np.array_equal(seen[0], pos) and np.array_equal(seen[1], quat):
                continue
            self._placed[name] = (pos, quat)
            body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
            move_fixed_body(self.mj, body, self.data.xpos[body].copy(), self.data.xquat[body].copy())

    def _draw_field(self, result: UncertaintyResult | None, centre: np.ndarray) -> None:
        if self.modes is not None:
            self.modes.remove()
            self.modes = None
        if result is None:
            self.field.visible = False
            return
        arrows = field_arrows(result, self.normalizer, np.asarray(centre))
        if self.field.points.shape != arrows.field.shape:
            self.field.remove()
            self.field = self.client.scene.add_arrows(
                f"/robots/{self.robot_id}/field/samples", arrows.field, arrows.colors, **FIELD_STYLE
            )
        else:
            self.field.colors = arrows.colors
            self.field.points = arrows.field
            self.field.visible = True
        if len(arrows.modes):
            self.modes = self.client.scene.add_arrows(
                f"/robots/{self.robot_id}/field/modes", arrows.modes, arrows.mode_colors, **MODE_STYLE
            )

    def show_target(self, on_drag: Callable[[np.ndarray, np.ndarray, str], None]) -> None:
        """The target gizmo at the current end-effector pose (nothing jumps); ``on_drag(pos, wxyz, phase)``."""
        if self.target is not None or self._frame is None:
            return
        self.target = self.client.scene.add_transform_controls(
            f"/robots/{self.robot_id}/target",
            scale=0.16,
            line_width=3.0,
            depth_test=False,
            position=self._frame.pos,
            wxyz=wxyz(self._frame.quat),
        )

        @self.target.on_update
        def _(event) -> None:
            handle = event.target
            on_drag(
                np.asarray(handle.position, float), np.asarray(handle.wxyz, float), getattr(event, "phase", "update")
            )

    def hide_target(self) -> None:
        if self.target is not None:
            self.target.remove()
            self.target = None

    def follow(self) -> None:
        """Moves an idle gizmo to the end effector, so the next drag starts from where the robot is."""
        if self.target is not None and self._frame is not None:
            self.target.position, self.target.wxyz = self._frame.pos, wxyz(self._frame.quat)

    def remove(self) -> None:
        self.client.scene.reset()


def pose_delta(pos: np.ndarray, quat_wxyz: np.ndarray, frame: RobotFrame) -> tuple[np.ndarray, np.ndarray]:
    """The world-frame delta (translation m, rotation vector rad) from the robot's pose to a target pose."""
    target = Rotation.from_quat([quat_wxyz[1], quat_wxyz[2], quat_wxyz[3], quat_wxyz[0]])
    rot = (target * Rotation.from_quat(frame.quat).inv()).as_rotvec()
    return np.asarray(pos, float) - frame.pos, rot

"""Action space and the one teleoperation command type.

Action vector layout (absolute end-effector target in the world frame, 10 dims)::

    [0:3]  position x, y, z (m)            -- the first three dims, always
    [3:9]  rotation, 6D (first two columns of the rotation matrix)
    [9]    gripper, -1 open .. +1 closed

``ActionSpace`` maps actions to and from a per-dimension [0, 1] normalisation:
position over the task's workspace bounds, 6D rotation components over
[-1, 1], gripper over [-1, 1]. Policies normalize their actions over the same
bounds (``hitl train``), so the paper's sampling radius r = 0.05 lives in this
space: on a 0.45 m workspace axis it is 2.25 cm of end-effector motion
(``ActionSpace.radius_in_units``; ``hitl tasks`` prints it per task).

``TeleopCommand`` is the only way an operator (human or scripted) moves a robot:
a delta pose and a gripper command, turned into an absolute action from the
robot's current pose by ``ActionSpace.apply_teleop``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from sim.rotations import mat_to_rot6d, rot6d_to_mat

POS = slice(0, 3)
ROT6D = slice(3, 9)
GRIPPER = 9
ACTION_DIM = 10
ACTION_LABELS = ("x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "gripper")


@dataclass(frozen=True)
class TeleopLimits:
    """Safe per-step sizes; larger deltas are scaled down to these norms."""

    max_delta_pos: float = 0.03  # metres per control step (0.6 m/s at 20 Hz)
    max_delta_rot: float = 0.2  # radians per control step

    def __post_init__(self) -> None:
        for name in ("max_delta_pos", "max_delta_rot"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"TeleopLimits.{name} must be a positive finite number, got {value!r}")


@dataclass(frozen=True)
class TeleopCommand:
    """Delta end-effector pose plus gripper command.

    Attributes:
        delta_pos: (3,) translation in metres, world frame.
        delta_rot: (3,) rotation vector in radians, world frame (pre-multiplied).
        gripper: -1 open .. +1 closed; values outside are clamped.

    Non-finite values are rejected here with ``ValueError``; magnitudes are
    clamped later against ``TeleopLimits`` so that a command is never lost.
    """

    delta_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delta_rot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gripper: float = -1.0

    def __post_init__(self) -> None:
        for name in ("delta_pos", "delta_rot"):
            raw = getattr(self, name)
            try:
                values = tuple(float(v) for v in raw)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"TeleopCommand.{name} must be 3 numbers, got {raw!r}") from exc
            if len(values) != 3:
                raise ValueError(f"TeleopCommand.{name} must have 3 components, got {len(values)}: {raw!r}")
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"TeleopCommand.{name} must be finite, got {values!r}")
            object.__setattr__(self, name, values)
        try:
            grip = float(self.gripper)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"TeleopCommand.gripper must be a number, got {self.gripper!r}") from exc
        if not math.isfinite(grip):
            raise ValueError(f"TeleopCommand.gripper must be finite, got {grip!r}")
        object.__setattr__(self, "gripper", grip)

    def clamped(self, limits: TeleopLimits) -> TeleopCommand:
        """The same direction, scaled down to the safe step sizes."""
        return TeleopCommand(
            delta_pos=tuple(_clip_norm(np.array(self.delta_pos), limits.max_delta_pos)),
            delta_rot=tuple(_clip_norm(np.array(self.delta_rot), limits.max_delta_rot)),
            gripper=float(np.clip(self.gripper, -1.0, 1.0)),
        )


@dataclass(frozen=True)
class TeleopTarget:
    """Result of applying a command: the absolute action and what was limited."""

    action: np.ndarray
    clamped: tuple[str, ...] = ()


@dataclass(frozen=True)
class ActionSpace:
    """Absolute end-effector pose + gripper, with [0, 1] normalisation.

    Args:
        pos_low, pos_high: (3,) workspace bounds in metres, world frame. Targets
            are kept inside them.
        limits: safe per-step teleoperation sizes.
    """

    pos_low: tuple[float, float, float]
    pos_high: tuple[float, float, float]
    limits: TeleopLimits = field(default_factory=TeleopLimits)

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.pos_low, float), np.asarray(self.pos_high, float)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"workspace bounds must be 3-vectors, got {self.pos_low!r}, {self.pos_high!r}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
            raise ValueError(
                f"workspace bounds need finite pos_low < pos_high, got {self.pos_low!r}, {self.pos_high!r}"
            )

    @property
    def dim(self) -> int:
        return ACTION_DIM

    @property
    def low(self) -> np.ndarray:
        return np.concatenate([np.asarray(self.pos_low, float), -np.ones(6), [-1.0]])

    @property
    def high(self) -> np.ndarray:
        return np.concatenate([np.asarray(self.pos_high, float), np.ones(6), [1.0]])

    def normalize(self, action: np.ndarray) -> np.ndarray:
        """(..., 10) actions -> (..., 10) in [0, 1] over the bounds."""
        lo, hi = self.low, self.high
        return (np.asarray(action, dtype=np.float64) - lo) / (hi - lo)

    def denormalize(self, unit: np.ndarray) -> np.ndarray:
        """(..., 10) values in [0, 1] -> (..., 10) actions."""
        lo, hi = self.low, self.high
        return np.asarray(unit, dtype=np.float64) * (hi - lo) + lo

    def radius_in_units(self, r: float) -> dict[str, object]:
        """What a radius r in the normalised space spans in each dimension's own units: position in
        centimetres per axis (x, y, z), and the 6D rotation and gripper components."""
        span = self.high - self.low
        return {
            "r": r,
            "position_cm": [round(float(v) * r * 100, 2) for v in span[POS]],
            "rot6d": round(float(span[ROT6D][0]) * r, 4),
            "gripper": round(float(span[GRIPPER]) * r, 4),
        }

    def make_action(self, pos: np.ndarray, rotmat: np.ndarray, gripper: float) -> np.ndarray:
        return np.concatenate([pos, mat_to_rot6d(rotmat), [gripper]])

    def validate(self, action: np.ndarray) -> np.ndarray:
        """Checks shape and finiteness; clips position into the workspace."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            bad = [ACTION_LABELS[i] for i in np.flatnonzero(~np.isfinite(action))]
            raise ValueError(f"action has non-finite values in {bad}")
        out = action.copy()
        out[POS] = np.clip(out[POS], self.pos_low, self.pos_high)
        out[GRIPPER] = np.clip(out[GRIPPER], -1.0, 1.0)
        return out

    def apply_teleop(self, command: TeleopCommand, pos: np.ndarray, rotmat: np.ndarray) -> TeleopTarget:
        """Absolute action from the current pose (pos (3,), rotmat (3, 3)) and a command."""
        safe = command.clamped(self.limits)
        clamped: list[str] = []
        if not np.allclose(safe.delta_pos, command.delta_pos):
            clamped.append("delta_pos")
        if not np.allclose(safe.delta_rot, command.delta_rot):
            clamped.append("delta_rot")
        if safe.gripper != command.gripper:
            clamped.append("gripper")
        raw_target = np.asarray(pos, float) + np.asarray(safe.delta_pos)
        target = np.clip(raw_target, self.pos_low, self.pos_high)
        if not np.allclose(target, raw_target):
            clamped.append("workspace")
        rot = Rotation.from_rotvec(safe.delta_rot).as_matrix() @ rot6d_to_mat(mat_to_rot6d(rotmat))
        return TeleopTarget(self.make_action(target, rot, safe.gripper), tuple(clamped))


def _clip_norm(v: np.ndarray, max_norm: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= max_norm else v * (max_norm / n)

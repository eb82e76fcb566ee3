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
robot's current pose by ``ActionSpace.apply_teleop``. It validates itself on construction and is the
one owner of an operator's command bounds and of its wire form (``to_dict``/``from_dict``): the API's body
model, the console, the operator bot and the recorder go through it.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

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
    """Delta end-effector pose plus gripper command: the one teleop command type, its validation and
    its wire form.

    Attributes:
        delta_pos: (3,) translation in metres, world frame.
        delta_rot: (3,) rotation vector in radians, world frame (pre-multiplied).
        gripper: -1 open .. +1 closed (``clamped`` brings a value outside into that range).

    Construction checks the form, for every command: 3 finite real numbers each for ``delta_pos`` and
    ``delta_rot``, a finite real number for ``gripper`` (``True``/``False`` refused), stored as Python
    floats; a ``ValueError`` names the field. It does not check sizes: the service composes the commands
    that arrive between two ticks and the scripted experts aim at far targets, and those are clamped to
    ``TeleopLimits`` when applied (``clamped``), so that a command is never lost.

    An operator's command is bounded per component (``MAX_DELTA_POS``, ``MAX_DELTA_ROT``,
    ``GRIPPER_RANGE``; the API's body schema states the same bounds from these constants): ``checked``,
    ``check_bounds`` and ``from_dict``/``from_json`` refuse one outside them. ``to_dict``/``to_json`` give
    its wire form (the body of ``POST /api/v1/robots/{id}/command``), which ``from_dict``/``from_json`` read
    back exactly.
    """

    delta_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delta_rot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gripper: float = -1.0

    # what an operator may send, per component (the robot clamps further, per step: ``TeleopLimits``)
    MAX_DELTA_POS: ClassVar[float] = 0.1  # m per command and component
    MAX_DELTA_ROT: ClassVar[float] = 0.5  # rad per command and component
    GRIPPER_RANGE: ClassVar[tuple[float, float]] = (-1.0, 1.0)  # open .. closed
    FIELDS: ClassVar[tuple[str, str, str]] = ("delta_pos", "delta_rot", "gripper")

    def __post_init__(self) -> None:
        object.__setattr__(self, "delta_pos", _vector3("delta_pos", self.delta_pos))
        object.__setattr__(self, "delta_rot", _vector3("delta_rot", self.delta_rot))
        object.__setattr__(self, "gripper", _finite("gripper", self.gripper))

    # -- bounds -------------------------------------------------------------------------------------------
    @classmethod
    def checked(
        cls,
        delta_pos: Sequence[float] = (0.0, 0.0, 0.0),
        delta_rot: Sequence[float] = (0.0, 0.0, 0.0),
        gripper: float = -1.0,
    ) -> TeleopCommand:
        """An operator's command: constructed, then ``check_bounds``."""
        return cls(delta_pos, delta_rot, gripper).check_bounds()

    def check_bounds(self) -> TeleopCommand:
        """``self`` when every component is within the bounds an operator may send, else a ``ValueError``
        naming the field."""
        for name, bound in (("delta_pos", self.MAX_DELTA_POS), ("delta_rot", self.MAX_DELTA_ROT)):
            values = getattr(self, name)
            if not all(-bound <= v <= bound for v in values):
                raise ValueError(f"TeleopCommand.{name}: each component must be within ±{bound}, got {values!r}")
        lo, hi = self.GRIPPER_RANGE
        if not lo <= self.gripper <= hi:
            raise ValueError(f"TeleopCommand.gripper must be within [{lo}, {hi}], got {self.gripper!r}")
        return self

    # -- wire form ----------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, list[float] | float]:
        """``{"delta_pos": [x, y, z], "delta_rot": [x, y, z], "gripper": g}``, Python floats (JSON-ready)."""
        return {"delta_pos": list(self.delta_pos), "delta_rot": list(self.delta_rot), "gripper": self.gripper}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), allow_nan=False)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, bounded: bool = True) -> TeleopCommand:
        """The command in ``data``, a wire form as the API's body takes it: ``delta_pos`` and ``gripper``
        required, ``delta_rot`` defaulting to no rotation, no other key. ``bounded``: refuse values outside
        the operator's bounds (``check_bounds``); False reads back any valid command (a composed one)."""
        if not isinstance(data, Mapping):
            raise ValueError(f"TeleopCommand must be a JSON object, got {type(data).__name__}")
        unknown = sorted(str(k) for k in data if k not in cls.FIELDS)
        if unknown:
            raise ValueError(f"TeleopCommand has unknown fields {unknown}; it takes {list(cls.FIELDS)}")
        for name in ("delta_pos", "gripper"):
            if name not in data:
                raise ValueError(f"TeleopCommand.{name} is missing")
        command = cls(data["delta_pos"], data.get("delta_rot", (0.0, 0.0, 0.0)), data["gripper"])
        return command.check_bounds() if bounded else command

    @classmethod
    def from_json(cls, text: str | bytes, *, bounded: bool = True) -> TeleopCommand:
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise ValueError(f"TeleopCommand: not valid JSON ({exc})") from None
        return cls.from_dict(data, bounded=bounded)

    def clamped(self, limits: TeleopLimits) -> TeleopCommand:
        """The same direction, scaled down to the safe step sizes."""
        return TeleopCommand(
            delta_pos=tuple(_clip_norm(np.array(self.delta_pos), limits.max_delta_pos)),
            delta_rot=tuple(_clip_norm(np.array(self.delta_rot), limits.max_delta_rot)),
            gripper=float(np.clip(self.gripper, *self.GRIPPER_RANGE)),
        )


def _real(name: str, v: object) -> float:
    """``v`` as a float, if it is a real number (not a bool); else a ``ValueError`` naming the field."""
    if type(v) is float:  # the common cases, first
        return v
    if isinstance(v, float):  # numpy's float64
        return float(v)
    if isinstance(v, bool | np.bool_) or not isinstance(v, numbers.Real):
        raise ValueError(f"TeleopCommand.{name} must be a number, got {v!r}")
    try:
        return float(v)
    except OverflowError:  # an int past a float's range
        raise ValueError(f"TeleopCommand.{name} must be finite, got {v!r}") from None


def _finite(name: str, v: object) -> float:
    value = _real(name, v)
    if value - value != 0.0:  # NaN or an infinity (math.isfinite, without the call)
        raise ValueError(f"TeleopCommand.{name} must be finite, got {value!r}")
    return value


def _vector3(name: str, raw: object) -> tuple[float, float, float]:
    if isinstance(raw, str | bytes | Mapping):
        raise ValueError(f"TeleopCommand.{name} must be 3 numbers, got {raw!r}")
    try:
        items = tuple(raw)
    except TypeError:
        raise ValueError(f"TeleopCommand.{name} must be 3 numbers, got {raw!r}") from None
    if len(items) != 3:
        raise ValueError(f"TeleopCommand.{name} must have 3 components, got {len(items)}: {raw!r}")
    x, y, z = items
    try:
        values = (_real(name, x), _real(name, y), _real(name, z))
    except ValueError:
        raise ValueError(f"TeleopCommand.{name} must be 3 numbers, got {raw!r}") from None
    if (values[0] - values[0]) + (values[1] - values[1]) + (values[2] - values[2]) != 0.0:  # NaN or infinity
        raise ValueError(f"TeleopCommand.{name} must be finite, got {values!r}")
    return values


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

"""Operator commands between ticks: every accepted command is applied exactly once, in order.

Commands that arrive between two control ticks compose into the one command the next tick applies:
translations add up, rotations compose in arrival order (world frame, each pre-multiplied), and the
newest gripper command wins. A command whose composition with those already waiting would exceed
the per-step limits (``TeleopLimits``: 3 cm and 0.2 rad) is refused with 429, and nothing already
accepted changes; the client sends it again after the next tick. A lone command over the limits is
accepted and clamped when applied, as the target reports.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation

from server.errors import ServiceError
from sim.spaces import TeleopCommand, TeleopLimits

_TOLERANCE = 1e-9


def compose(first: TeleopCommand, then: TeleopCommand) -> TeleopCommand:
    """``first`` followed by ``then``, as one command."""
    rot = Rotation.from_rotvec(then.delta_rot) * Rotation.from_rotvec(first.delta_rot)
    pos = np.add(first.delta_pos, then.delta_pos)
    return TeleopCommand(tuple(pos), tuple(rot.as_rotvec()), then.gripper)


class CommandMailbox:
    """One robot's commands waiting for the next tick (thread-safe)."""

    def __init__(self, limits: TeleopLimits) -> None:
        self.limits = limits
        self._lock = threading.Lock()
        self._pending: TeleopCommand | None = None
        self._since: float | None = None  # when the oldest waiting command arrived (monotonic)
        self.count = 0  # commands composed into the pending one

    def put(self, command: TeleopCommand) -> int:
        """Accepts ``command`` for the next tick; returns how many commands that tick will apply."""
        with self._lock:
            if self._pending is None:
                self._pending, self._since, self.count = command, time.monotonic(), 1
                return 1
            merged = compose(self._pending, command)
            pos, rot = np.linalg.norm(merged.delta_pos), np.linalg.norm(merged.delta_rot)
            if pos > self.limits.max_delta_pos + _TOLERANCE or rot > self.limits.max_delta_rot + _TOLERANCE:
                raise ServiceError(
                    429,
                    f"{self.count} command(s) already wait for the next control tick; with this one the step "
                    f"would move {pos * 100:.1f} cm and turn {rot:.3f} rad, over the per-step limits "
                    f"({self.limits.max_delta_pos * 100:.0f} cm, {self.limits.max_delta_rot} rad): "
                    "send it again after the next tick",
                )
            self._pending = merged
            self.count += 1
            return self.count

    def take(self) -> tuple[TeleopCommand, float, int] | None:
        """(the composed command, when its first part arrived, how many) and empties the mailbox."""
        with self._lock:
            if self._pending is None:
                return None
            out = (self._pending, self._since, self.count)
            self._pending, self._since, self.count = None, None, 0
            return out

    def clear(self) -> None:
        with self._lock:
            self._pending, self._since, self.count = None, None, 0

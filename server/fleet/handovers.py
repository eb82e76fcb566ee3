"""Claims and releases on their way to the control loop.

The control loop holds the fleet lock for a whole tick, batched policy and uncertainty included
(``server.fleet.loop``). A claim or a release that took that lock waited for the tick in progress:
it was the largest part of the API's latency under load (``docs/benchmarks/service.md``). So the API
decides them where they are decided, in the assistance queue under its own lock (who holds the
robot, the lease), and puts the change of control in the robot's ``HandoverMailbox``; the loop
applies it at the start of its next tick, under the fleet lock, before it steps anyone
(``Lifecycle.apply_handovers``). Until then the robot is shown in the mode the handovers
will give it (``shown_mode``), and commands from the operator who claimed it are accepted, as they
are once the claim is applied: they wait in the command mailbox for the same tick.

A handover is applied only if the queue still agrees when the tick comes: a claim whose request has
ended (the episode ended, the robot was reset) or whose lease has run out in between changes
nothing, as if it had come a moment later.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Literal

from server.fleet.modes import FleetMode


@dataclass(frozen=True)
class Handover:
    kind: Literal["claim", "release"]
    operator: str


class HandoverMailbox:
    """One robot's claims and releases accepted and not yet applied, in order. The loop removes them
    only once applied and published (``applied``), so a reader that takes ``pending()`` before the
    published view sees each handover either still pending or already in the view, never neither."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[Handover] = []

    def put(self, handover: Handover) -> None:
        with self._lock:
            self._items.append(handover)

    def pending(self) -> list[Handover]:
        with self._lock:
            return list(self._items)

    def applied(self, n: int) -> None:
        """The first ``n`` pending handovers are applied and published."""
        with self._lock:
            del self._items[:n]

    def shown_mode(self, mode: FleetMode, pending: list[Handover] | None = None) -> FleetMode:
        """The mode the robot will be in once the pending handovers (``pending``: as read before ``mode``)
        apply, from its ``mode`` now: a claim puts a waiting robot under teleop, a release hands a robot
        under teleop back."""
        for h in self.pending() if pending is None else pending:
            if h.kind == "claim" and mode == FleetMode.WAITING:
                mode = FleetMode.TELEOP
            elif h.kind == "release" and mode == FleetMode.TELEOP:
                mode = FleetMode.AUTONOMOUS
        return mode

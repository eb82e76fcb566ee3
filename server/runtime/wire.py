"""What crosses between the fleet runtime's process and the API processes (``server.runtime``).

Messages are pickled by ``multiprocessing.connection`` on a socket authenticated with a shared key
(HMAC challenge at connect): only a process given the key can connect, and a connection that fails the
challenge is closed before anything is unpickled. Keep the key secret: a holder of it can run code in
either process, as with any pickle channel.

A ``RobotView`` crosses with its policy slot replaced by a ``SlotRef`` (version, folder, task,
lineage): the slot holds the loaded network and controller, which the API process loads itself, once
per version, from the same folder (``server.runtime.client.SlotCache``).

Every answer carries ``t``, the runtime's ``time.monotonic()`` taken before it read what it sends, so
an API process keeps, of two copies of a robot, the one read later: a snapshot read before a claim
never hides the claim that the claimant's own answer showed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from server.finetune.scheduler import ScheduleStatus
from server.fleet.assistance import AssistanceRequest
from server.fleet.metrics import MetricsReport
from server.fleet.robot import RobotView

# The FleetPort members an API process calls on the runtime; those that change a robot's mode answer
# with its view as the runtime shows it after the call (a heartbeat or a command changes no mode).
CALLS = frozenset(
    {
        "claim",
        "heartbeat",
        "command",
        "release",
        "pause",
        "resume",
        "reset",
        "register_policy",
        "activate_policy",
        "camera_view",
    }
)
ROBOT_CALLS = frozenset({"claim", "release", "pause", "resume", "reset"})
Channel = Literal["calls", "snapshots"]


@dataclass(frozen=True)
class SlotRef:
    """A policy slot as it crosses: what the other side needs to load the same version."""

    version: int
    path: Path
    task: str
    lineage: str


@dataclass(frozen=True)
class Hello:
    """A connection's first message: what it is for, and who opens it (logged by the runtime)."""

    channel: Channel
    who: str


@dataclass(frozen=True)
class Call:
    method: str
    args: tuple


@dataclass(frozen=True)
class Reply:
    """``error``: (HTTP status, message) of the ``ServiceError`` the call raised, else None."""

    value: Any = None
    error: tuple[int, str] | None = None
    t: float = 0.0
    view: RobotView | None = None


@dataclass(frozen=True)
class Snapshot:
    """What the runtime publishes, ``publish_hz`` times a second: the robots whose view changed since
    the previous snapshot (all of them in a subscriber's first), the open requests, and, when due, the
    fleet metrics and the nightly job's schedule."""

    t: float
    ticks: int
    views: dict[int, RobotView]
    requests: list[AssistanceRequest]
    robots: tuple[int, ...]
    metrics: MetricsReport | None = None
    schedule: ScheduleStatus | None = None
    full: bool = False


@dataclass(frozen=True)
class TimelineTail:
    """A robot's timeline as it crosses: every point (``whole``), or those from the clock of the last
    point sent before on (the last one may have changed since: ``Robot.record`` updates a point at the
    same clock). The timeline is most of a view's objects; sending it whole at every snapshot cost the
    API process more time unpickling than serving requests."""

    points: tuple
    whole: bool


def portable(view: RobotView, since: int | None = None) -> RobotView:
    """``view`` with its slot replaced by a ``SlotRef``, and its timeline by a ``TimelineTail`` (from
    clock ``since`` on; None: whole)."""
    slot, timeline = view.slot, view.timeline
    if isinstance(slot, SlotRef):
        return view
    if since is None:
        tail = TimelineTail(tuple(timeline), whole=True)
    else:
        start = len(timeline)
        while start > 0 and timeline[start - 1].t >= since:
            start -= 1
        tail = TimelineTail(tuple(timeline[start:]), whole=False)
    return replace(view, slot=SlotRef(slot.version, Path(slot.path), slot.task, slot.lineage), timeline=tail)


def timeline_since(view: RobotView) -> tuple[int | None, int | None]:
    """(episode, clock of its last timeline point): where the next ``TimelineTail`` of the robot starts."""
    return view.episode_id, (view.timeline[-1].t if view.timeline else None)


@dataclass(frozen=True)
class RuntimeLink:
    """Where an API process finds the fleet runtime, and the key its connections authenticate with."""

    address: tuple[str, int]
    authkey: bytes = field(repr=False)

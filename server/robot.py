"""A fleet robot: its record in the runtime (``Robot``) and the copy the API reads (``RobotView``)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING

from policy.uncertainty import UncertaintyResult
from server.commands import CommandMailbox
from server.handovers import HandoverMailbox
from server.slots import PolicySlot
from server.workers import RobotWorker
from sim.frame import RobotFrame
from storage.episodes import EpisodeWriter
from storage.segments import SegmentWriter

if TYPE_CHECKING:  # server.recording imports this module
    from server.recording import PendingStep

MODES = ("autonomous", "waiting", "teleop", "paused", "done", "faulted")
U_HISTORY = 300


@dataclass(frozen=True)
class TimelinePoint:
    """One step of a robot's recent history, as the console plots it: t (the episode's clock: policy and
    operator steps; holds while waiting do not advance it), the mode after it, the asking signal's score
    (None when not scored: waiting, or teleop without a command) and the denoising metric's U (None when
    not computed); asked / handed: at this step the robot asked for help / control changed hands (set by
    ``Robot.record`` from the modes)."""

    t: int
    mode: str
    score: float | None
    U: float | None
    asked: bool = False
    handed: bool = False


@dataclass(frozen=True)
class RobotView:
    """A robot as the API shows it, copied at the end of each tick and after each service call."""

    id: int
    task: str
    slot: PolicySlot
    seed: int
    mode: str
    episode_id: int | None
    steps: int
    u_history: tuple
    frame: RobotFrame | None
    last_result: UncertaintyResult | None
    episodes_done: int
    successes: int
    assisted_steps: int
    events: int
    restarts: int
    fault: str | None
    scores: dict
    teleop_left: int | None
    timeline: tuple


@dataclass
class Robot:
    id: int
    task: str
    slot: PolicySlot
    seed: int
    commands: CommandMailbox
    worker: RobotWorker | None = None
    mode: str = "autonomous"
    frame: RobotFrame | None = None
    fresh: bool = False  # ``frame`` arrived since the robot's last step
    episode_id: int | None = None
    steps: int = 0
    assisted_steps: int = 0
    events: int = 0
    episodes_done: int = 0
    successes: int = 0
    u_history: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))
    last_result: UncertaintyResult | None = None
    scores: dict = field(default_factory=dict)  # every signal's score at the last scored step
    teleop_left: int | None = None  # operator steps left in a budgeted assistance event
    timeline: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))  # TimelinePoint per step
    restarts: int = 0
    restart_at: float | None = None
    fault: str | None = None
    fault_pending: str | None = None  # a worker fault seen while the controller was stepping: applied after it
    paused_from: str | None = None
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))  # command arrival -> sent (s)
    action_periods: deque = field(default_factory=lambda: deque(maxlen=1000))  # seconds between actions sent
    last_sent: float | None = None
    segment: SegmentWriter | None = None
    segment_id: int | None = None
    recorder: EpisodeWriter | None = None  # whole-episode recording (settings.record_episodes)
    pending_step: PendingStep | None = None  # the step sent, written once its outcome arrives
    view: RobotView | None = None  # what readers see (``Fleet._publish``)
    handovers: HandoverMailbox = field(default_factory=HandoverMailbox)  # claims, releases for the next tick

    def publish(self) -> None:
        """A consistent copy of what the API shows, so readers never wait for a tick in progress."""
        values = {f.name: getattr(self, f.name) for f in fields(RobotView)}
        self.view = RobotView(**values | {"u_history": tuple(self.u_history), "timeline": tuple(self.timeline)})

    def record(self, point: TimelinePoint) -> None:
        """Appends a step to the timeline. At the same clock (a robot holding while it waits) the last point
        takes the new mode and keeps the scores it had when the new point has none."""
        last = self.timeline[-1] if self.timeline else None
        before = last.mode if last is not None else point.mode
        steady = "paused" in (before, point.mode)  # pausing and resuming change nothing for the plot
        asked = not steady and point.mode == "waiting" and before != "waiting"
        handed = not steady and (point.mode == "teleop") != (before == "teleop")
        if last is None or last.t != point.t:
            self.timeline.append(replace(point, asked=asked, handed=handed))
            return
        self.timeline[-1] = TimelinePoint(
            point.t,
            point.mode,
            point.score if point.score is not None else last.score,
            point.U if point.U is not None else last.U,
            asked=last.asked or asked,
            handed=last.handed or handed,
        )

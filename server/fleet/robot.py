"""A fleet robot: its record in the fleet (``Robot``) and the copy the API reads (``RobotView``).

``Robot`` holds what the fleet knows of one robot: its worker, policy slot, episode and counters. Its
mode and the hand-back rule's counters are its ``control`` (``policy.hitl_state.RobotControl``), the one
record the controller steps too (``Controller.reset`` is given it): a paused robot stays paused through
the transitions the loop makes meanwhile, and resumes into the mode they left it in. ``Robot.ask`` is
the record of the robot's open assistance request, the queue's own (``server.fleet.assistance.AskRecord``):
set where the request is opened, cleared where it closes
(``server.fleet.lifecycle.Lifecycle.end_takeover``). The recorder's per-robot state (open files, the
step waiting for its outcome) is the recorder's own (``server.fleet.recording``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, fields, replace

from policy.hitl_state import Mode, RobotControl
from policy.uncertainty import UncertaintyResult
from server.fleet.assistance import AskRecord
from server.fleet.inbox import Inbox
from server.fleet.slots import PolicySlot
from server.workers import RobotWorker
from sim.frame import RobotFrame

U_HISTORY = 300


@dataclass(frozen=True)
class TimelinePoint:
    """One step of a robot's recent history, as the console plots it: t (the episode's clock: policy and
    operator steps; holds while waiting do not advance it), the mode after it, the asking signal's score
    (None when not scored: waiting, or teleop without a command) and the denoising metric's U (None when
    not computed); asked / handed: at this step the robot asked for help / control changed hands (set by
    ``Robot.record`` from the modes)."""

    t: int
    mode: Mode
    score: float | None
    U: float | None
    asked: bool = False
    handed: bool = False


@dataclass(frozen=True)
class RobotView:
    """A robot as the API shows it, copied at the end of each tick and after each service call.
    u_history: the paper's denoising U per scored step; score_history: the asking signal's score per
    scored step; scores / wants: every signal's score and decision at the last scored step; ask: the
    open request's record (None when the robot has none)."""

    id: int
    task: str
    slot: PolicySlot
    seed: int
    mode: Mode
    episode_id: int | None
    steps: int
    u_history: tuple
    score_history: tuple
    frame: RobotFrame | None
    last_result: UncertaintyResult | None
    episodes_done: int
    successes: int
    assisted_steps: int
    events: int
    restarts: int
    fault: str | None
    scores: dict
    wants: dict
    ask: AskRecord | None
    teleop_left: int | None
    timeline: tuple


@dataclass
class Robot:
    id: int
    task: str
    slot: PolicySlot
    seed: int
    inbox: Inbox  # what the API asked, for the loop's next tick (``server.fleet.inbox``)
    worker: RobotWorker | None = None
    images: bool = False  # its worker renders the policy's cameras (the policy it was started for sees them)
    frame: RobotFrame | None = None
    fresh: bool = False  # ``frame`` arrived since the robot's last step
    episode_id: int | None = None
    steps: int = 0
    assisted_steps: int = 0
    events: int = 0
    episodes_done: int = 0
    successes: int = 0
    u_history: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))  # the paper's U per scored step
    score_history: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))  # the asking signal's score
    last_result: UncertaintyResult | None = None
    scores: dict = field(default_factory=dict)  # every signal's score at the last scored step
    wants: dict = field(default_factory=dict)  # every signal's decision at the last scored step
    ask: AskRecord | None = None  # the open assistance request's record (the queue's)
    timeline: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))  # TimelinePoint per step
    restarts: int = 0
    restart_at: float | None = None
    fault: str | None = None
    fault_pending: str | None = None  # a worker fault seen while the controller was stepping: applied after it
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))  # command arrival -> sent (s)
    action_periods: deque = field(default_factory=lambda: deque(maxlen=1000))  # seconds between actions sent
    last_sent: float | None = None
    view: RobotView | None = None  # what readers see (``publish``)
    control: RobotControl = field(default_factory=RobotControl)  # mode and counters (``policy.hitl_state``)

    @property
    def mode(self) -> Mode:
        return self.control.mode

    @property
    def teleop_left(self) -> int | None:
        """Operator steps left in a budgeted assistance event (None: not under teleop, or continuous)."""
        return self.control.teleop_left

    def publish(self) -> None:
        """A consistent copy of what the API shows, so readers never wait for a tick in progress."""
        values = {f.name: getattr(self, f.name) for f in fields(RobotView)}
        copies = {name: tuple(getattr(self, name)) for name in ("u_history", "score_history", "timeline")}
        self.view = RobotView(**values | copies)

    def record(self, point: TimelinePoint) -> None:
        """Appends a step to the timeline. At the same clock (a robot holding while it waits) the last point
        takes the new mode and keeps the scores it had when the new point has none."""
        last = self.timeline[-1] if self.timeline else None
        before = last.mode if last is not None else point.mode
        steady = Mode.PAUSED in (before, point.mode)  # pausing and resuming change nothing for the plot
        asked = not steady and point.mode == Mode.WAITING and before != Mode.WAITING
        handed = not steady and (point.mode == Mode.TELEOP) != (before == Mode.TELEOP)
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

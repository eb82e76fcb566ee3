"""The assistance queue: open requests ordered by urgency and waiting time; a claim is a lease.

One controller per robot. A claim lasts ``lease_seconds`` and is renewed by heartbeats; when it
expires the request returns to the queue (the robot holds meanwhile). Thread-safe.

**Order.** ``priority = urgency + waited / wait_scale`` (``wait_scale`` 10 s), highest first, claimed
requests last. The urgency says how far the asking score is over its threshold, as a fraction of the
score: ``1 - threshold / score`` when ``score > threshold > 0``, so it lies in [0, 1) whatever the
signal's scale, and within one signal a higher score still ranks first: signals' scales differ by
orders of magnitude, and ranked by ``score / threshold`` a fresh request of one signal far over its
threshold would go ahead of another's that has waited for hours. A request that gives no scale to
measure the score against has urgency 0 and ranks by its wait alone: the watchdog's and an
operator's requests (opened with score = threshold = 1, where a score's urgency is 0), a threshold
that is not positive and finite (a signal told to ask at every step, or one whose zero means nothing),
a score that is NaN. A score of +inf has urgency 1.

**No robot starves.** Two urgencies differ by at most 1, so a request opened more than
``wait_scale`` after request A never ranks ahead of A while A waits. Once A has waited ``wait_scale``,
only requests already open then can be claimed before it: at most one per other robot (a robot has
one request at a time), the queue's length. With operators claiming the head of the queue (as
``OperatorBot`` does; the order is advice, an operator may claim any robot), A waits at most
``wait_scale`` + queue length x time per takeover / operators (the length counts A and covers the
takeovers in progress). Lease expiries are not counted: a request whose lease ran out goes back with
its opening time, so one that was ahead of A is ahead again.

**Other orders** (``Settings.queue.order``, for comparing allocations; ``hitl bench operators``):
``"cur"`` is Fleet-DAgger's CUR allocation (Hoque et al., 2022): constraint violations first, then
uncertainty, then risk. A constraint violation is read as a stalled robot, one the watchdog asked for
(its episode used its share of the horizon without success; a faulted robot does not ask, it waits
for a reset); uncertainty is the urgency above; risk is left out, since nothing here estimates it.
Ties go to the request opened first. CUR has no waiting term, so a request can starve behind fresher,
more urgent ones. ``"fcfs"`` is first come, first served: the request opened first.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from dataclasses import dataclass, field

from policy.controller import WATCHDOG, Controller, RobotStep
from server.errors import ServiceError
from sim.frame import RobotFrame

WAIT_SCALE_S = 10.0  # seconds of waiting worth the whole urgency range
QUEUE_ORDERS = ("priority", "cur", "fcfs")  # ours (the default), Fleet-DAgger's CUR, first come first served


def urgency(score: float, threshold: float) -> float:
    """How far ``score`` is over ``threshold``, as a fraction of the score: ``1 - threshold / score`` in
    [0, 1] when ``score > threshold > 0`` (1 only for an infinite score), else 0 (see the module)."""
    if not (0 < threshold < math.inf) or not score > threshold:  # NaN compares False: 0
        return 0.0
    return 1.0 - threshold / score


@dataclass(frozen=True)
class AskRecord:
    """Why a robot asked for help: what its request holds, built here once and shown the same by the queue,
    the robot (``server.fleet.robot.Robot.ask``) and the takeover that answers it (``server.fleet.recording``).

    signal: the asking signal's name, ``policy.controller.WATCHDOG`` when the watchdog asked, None for
    help requested through the service (``Fleet.request_help``: drills, benchmarks); score, threshold:
    that signal's score at the step it asked and its threshold (1 and 1 for the watchdog and requested
    help: no scale, so they rank by their wait); reason: the words the queue shows; asked_at_step: the
    episode's clock at that step (None without a frame); paper_u: the paper's denoising U at that step
    (None when it was not computed)."""

    signal: str | None
    score: float
    threshold: float
    reason: str
    asked_at_step: int | None = None
    paper_u: float | None = None

    @classmethod
    def of_step(cls, step: RobotStep, controller: Controller, frame: RobotFrame) -> AskRecord:
        """The request of a step on which the robot asked (``step.asked``): its signal's, or the watchdog's."""
        paper_u = float(step.uncertainty.U) if step.uncertainty is not None else None
        if step.asked_by == WATCHDOG:
            reason = f"watchdog: {frame.clock} of {frame.horizon} steps without success"
            return cls(WATCHDOG, 1.0, 1.0, reason, frame.clock, paper_u)
        asking = controller.asking
        value, threshold = float(step.scores[asking]), float(controller.signals[asking].threshold)
        why = step.why or f"score {value:.3g} over {threshold:.3g}"
        return cls(asking, value, threshold, f"{asking}: {why}", frame.clock, paper_u)

    @classmethod
    def requested(cls, reason: str, frame: RobotFrame | None) -> AskRecord:
        """Help requested through the service, not by a signal (``Fleet.request_help``)."""
        return cls(None, 1.0, 1.0, reason, frame.clock if frame is not None else None)


@dataclass
class AssistanceRequest:
    """One robot's open request: ``score`` and ``threshold`` are the asking signal's (``AskRecord``), and
    ``ask`` the record it was opened with."""

    id: int
    robot_id: int
    score: float
    threshold: float
    reason: str
    created: float = field(default_factory=time.monotonic)
    created_wall: float = field(default_factory=time.time)
    holder: str | None = None
    lease_until: float | None = None
    claimed_at: float | None = None
    requeued: int = 0
    expired_holder: str | None = None  # who held the lease that ran out last
    released: bool = False  # its holder handed the robot back; the loop closes it at its next tick
    signal: str | None = None
    asked_at_step: int | None = None
    paper_u: float | None = None

    @property
    def ask(self) -> AskRecord:
        """The record this request was opened with."""
        return AskRecord(self.signal, self.score, self.threshold, self.reason, self.asked_at_step, self.paper_u)

    def priority(self, now: float, wait_scale: float = WAIT_SCALE_S) -> float:
        """Higher first: the urgency (in [0, 1], whatever the signal's scale) plus one unit per
        ``wait_scale`` seconds waited; finite for every score and threshold (see the module)."""
        return urgency(self.score, self.threshold) + (now - self.created) / wait_scale


def _sort_key(order: str, now: float):
    """The key that puts the request to claim next first, in ``order`` (see the module)."""
    if order == "priority":
        return lambda r: (-r.priority(now), r.created)
    if order == "cur":
        return lambda r: (r.signal != WATCHDOG, -urgency(r.score, r.threshold), r.created)
    if order == "fcfs":
        return lambda r: r.created
    raise ValueError(f"unknown queue order {order!r}: one of {', '.join(QUEUE_ORDERS)}")


class AssistanceQueue:
    def __init__(self, lease_seconds: float, order: str = "priority") -> None:
        """order: how ``pending`` ranks unclaimed requests, one of ``QUEUE_ORDERS`` (see the module)."""
        _sort_key(order, 0.0)  # refuses an unknown order here, not at the first claim
        self.lease_seconds = lease_seconds
        self.order = order
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._by_robot: dict[int, AssistanceRequest] = {}
        self.waits: list[float] = []  # seconds from request to claim, for metrics

    def ask(self, robot_id: int, record: AskRecord, now: float | None = None) -> AssistanceRequest:
        """The robot's open request, or a new one for ``record`` opened at ``now`` (default:
        ``time.monotonic()``). The robot shows the answer's ``ask``: what the queue holds."""
        with self._lock:
            if robot_id in self._by_robot:
                return self._by_robot[robot_id]
            created = time.monotonic() if now is None else now
            req = AssistanceRequest(
                next(self._ids),
                robot_id,
                record.score,
                record.threshold,
                record.reason,
                created=created,
                signal=record.signal,
                asked_at_step=record.asked_at_step,
                paper_u=record.paper_u,
            )
            self._by_robot[robot_id] = req
            return req

    def pending(self, now: float | None = None) -> list[AssistanceRequest]:
        """Open requests, unclaimed first, each part in the queue's order at ``now`` (default:
        ``time.monotonic()``)."""
        now = time.monotonic() if now is None else now
        key = _sort_key(self.order, now)
        with self._lock:
            requests = sorted(self._by_robot.values(), key=key)
        return sorted(requests, key=lambda r: r.holder is not None)  # stable: each part keeps the order

    def get(self, robot_id: int) -> AssistanceRequest | None:
        with self._lock:
            return self._by_robot.get(robot_id)

    def claim(self, robot_id: int, operator: str, now: float | None = None) -> AssistanceRequest:
        now = time.monotonic() if now is None else now
        with self._lock:
            req = self._by_robot.get(robot_id)
            if req is None:
                raise ServiceError(
                    409,
                    f"robot {robot_id} has no open assistance request: it is neither waiting for help nor under teleop",
                )
            if req.released:
                raise ServiceError(409, f"robot {robot_id} is being handed back to its policy")
            if req.holder is not None and req.holder != operator and req.lease_until and req.lease_until > now:
                raise ServiceError(409, f"robot {robot_id} is already controlled by another operator")
            if req.holder is None:
                self.waits.append(now - req.created)
            req.holder, req.lease_until, req.claimed_at = operator, now + self.lease_seconds, now
            return req

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest:
        with self._lock:
            req = self._holder_check(robot_id, operator)
            req.lease_until = time.monotonic() + self.lease_seconds
            return req

    def check_holder(self, robot_id: int, operator: str) -> AssistanceRequest:
        with self._lock:
            return self._holder_check(robot_id, operator)

    def release(self, robot_id: int, operator: str) -> AssistanceRequest:
        """``operator`` hands the robot back: from now on nothing of theirs is accepted for it, and the
        loop closes the request when it applies the hand-back."""
        with self._lock:
            req = self._holder_check(robot_id, operator)
            req.released = True
            return req

    def _holder_check(self, robot_id: int, operator: str) -> AssistanceRequest:
        req = self._by_robot.get(robot_id)
        if req is None:
            raise ServiceError(
                409, f"robot {robot_id} has no open assistance request: it is neither waiting for help nor under teleop"
            )
        if req.holder != operator:
            raise ServiceError(409, f"robot {robot_id} is not controlled by you: claim it first")
        if req.released:
            raise ServiceError(409, f"robot {robot_id} is being handed back to its policy")
        return req

    def close(self, robot_id: int) -> AssistanceRequest | None:
        with self._lock:
            return self._by_robot.pop(robot_id, None)

    def expire(self) -> list[AssistanceRequest]:
        """Returns claims whose lease ran out, now back in the queue."""
        now = time.monotonic()
        out = []
        with self._lock:
            for req in self._by_robot.values():
                held = req.holder is not None and not req.released
                if held and req.lease_until is not None and req.lease_until <= now:
                    req.expired_holder, req.holder, req.lease_until = req.holder, None, None
                    req.requeued += 1
                    out.append(req)
        return out

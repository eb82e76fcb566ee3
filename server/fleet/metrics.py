"""Fleet metrics: the figures of the API's ``/metrics/fleet`` (``MetricsReport``), and the operators' time
in control that they are made of (``OperatorClock``).

The operators' clock is kept where takeovers start and end (``server.fleet.fleet``: a first claim;
``server.fleet.lifecycle``: a takeover's end, a lease that ran out); the queue keeps its own waits. The
episode totals come from one aggregate query over the recorded episodes (``Recorder.totals``), run
outside the fleet lock, so a metrics request never holds up a tick.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from policy.hitl_state import MODES
from server.fleet.assistance import AssistanceQueue
from server.fleet.recording import EpisodeTotals
from server.fleet.robot import RobotView


class OperatorClock:
    """Per operator: seconds in control, and when they first claimed a robot (``time.monotonic``)."""

    def __init__(self) -> None:
        self.busy: dict[str, float] = {}
        self.since: dict[str, float] = {}

    def claimed(self, operator: str) -> None:
        self.since.setdefault(operator, time.monotonic())

    def add_busy(self, operator: str, seconds: float) -> None:
        self.busy[operator] = self.busy.get(operator, 0.0) + seconds


@dataclass(frozen=True)
class MetricsReport:
    """The fleet's figures (``server.api.schemas.FleetMetrics`` documents each)."""

    episodes: int
    success_rate: float | None
    assisted_steps_per_episode: float | None
    assistance_events_per_episode: float | None
    queue_wait_p50_s: float | None
    queue_wait_p95_s: float | None
    queue_wait_max_s: float | None
    queue_oldest_unclaimed_s: float | None
    operator_busy_s: dict[str, float]
    operator_idle_s: dict[str, float]
    return_on_human_effort: float | None
    robots_by_mode: dict[str, int]
    ticks: int


def report(
    totals: EpisodeTotals, queue: AssistanceQueue, clock: OperatorClock, views: Iterable[RobotView], ticks: int
) -> MetricsReport:
    """The fleet's figures from its episode totals, queue, operators' clock, robots and ticks."""
    n, success, assisted = totals.episodes, totals.successes, totals.assisted_steps
    waits = np.array(list(queue.waits))
    now = time.monotonic()
    unclaimed = [now - r.created for r in queue.pending(now) if r.holder is None]
    busy, since = dict(clock.busy), dict(clock.since)
    views = list(views)
    return MetricsReport(
        episodes=n,
        success_rate=success / n if n else None,
        assisted_steps_per_episode=assisted / n if n else None,
        assistance_events_per_episode=totals.events / n if n else None,
        queue_wait_p50_s=float(np.quantile(waits, 0.5)) if len(waits) else None,
        queue_wait_p95_s=float(np.quantile(waits, 0.95)) if len(waits) else None,
        queue_wait_max_s=float(waits.max()) if len(waits) else None,
        queue_oldest_unclaimed_s=max(unclaimed, default=None),
        operator_busy_s=busy,
        operator_idle_s={op: max(0.0, now - t0 - busy.get(op, 0.0)) for op, t0 in since.items()},
        return_on_human_effort=success / assisted if assisted else None,
        robots_by_mode={m.value: sum(v.mode == m for v in views) for m in MODES},
        ticks=ticks,
    )

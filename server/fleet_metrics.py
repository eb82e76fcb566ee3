"""Fleet metrics: the figures of the API's ``/metrics/fleet``, from the recorder's totals and the fleet's counters.

The counters themselves (``ticks``, ``operator_busy``, ``operator_since``, the queue's waits) live on
the fleet and are kept by the control loop and the operator methods where things happen; this module
only turns them into the report. The episode totals come from one aggregate query over the recorded
episodes, run outside the fleet lock, so a metrics request never holds up a tick.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from server.robot import MODES

if TYPE_CHECKING:
    from server.fleet import Fleet


def fleet_metrics(fleet: Fleet) -> dict:
    """Fleet metrics; the episode totals come from one aggregate query, outside the fleet lock."""
    totals = fleet.recorder.totals()
    n, success, assisted = totals["episodes"], totals["successes"], totals["assisted_steps"]
    waits = np.array(list(fleet.queue.waits))
    now = time.monotonic()
    unclaimed = [now - r.created for r in fleet.queue.pending(now) if r.holder is None]
    busy, since = dict(fleet.operator_busy), dict(fleet.operator_since)
    views = fleet.views()
    return {
        "episodes": n,
        "success_rate": success / n if n else None,
        "assisted_steps_per_episode": assisted / n if n else None,
        "assistance_events_per_episode": totals["events"] / n if n else None,
        "queue_wait_p50_s": float(np.quantile(waits, 0.5)) if len(waits) else None,
        "queue_wait_p95_s": float(np.quantile(waits, 0.95)) if len(waits) else None,
        "queue_wait_max_s": float(waits.max()) if len(waits) else None,
        "queue_oldest_unclaimed_s": max(unclaimed, default=None),
        "operator_busy_s": busy,
        "operator_idle_s": {op: max(0.0, now - t0 - busy.get(op, 0.0)) for op, t0 in since.items()},
        "return_on_human_effort": success / assisted if assisted else None,
        "robots_by_mode": {m: sum(v.mode == m for v in views) for m in MODES},
        "ticks": fleet.ticks,
    }

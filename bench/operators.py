"""``hitl bench operators``: how many robots one operator keeps working, measured through the real service.

A real ``hitl serve`` process runs a fleet of ``size`` robots mixed from tasks by share (``FleetMix``:
by default 70% lift-cube, the policy's own task, and 10% each of an unseen object, partial
observability and an ambiguous goal), with the settings of a config file (``configs/operators.toml``:
the fleet as ``make demo`` serves it, continuous hand-back and the watchdog; a policy its robot groups
name for a task drives that task's robots, the bundled one otherwise). One simulated operator (``OperatorBot``, the REST
API only) serves its queue at a person's pace (``Pace``: a delay to claim, a further delay to switch
to another robot, a minimum time per takeover, all in control ticks) for ``ticks`` ticks of the
fleet's clock. Fleet sizes are swept; each size is a fresh service.

**Clock.** The fleet's control rate is the config's, or ``control_hz`` when given. Where this machine
cannot step a fleet at 10 Hz the sweep runs on a slower clock and the report says so (``slowed``);
waits are reported in ticks as well as in seconds, and ticks are robot time whatever the clock. The
rate the fleet held is measured (``/metrics/fleet``'s tick count over the run's wall time) and a size
whose fleet fell more than 5% short of its clock is marked ``kept_clock: false``. No size that was not
run is reported.

**Per size and per task:** success rate of the episodes that ended during the run (one still running at
the end is not counted); queue waits from request to claim, p50 / p95 / max, in seconds and ticks, with
the requests still unclaimed at the end counted at their age so far; takeovers opened during the run and
the steps the operator drove in them (those of episodes still running at the end too); return on human
effort (ROHE: successes per operator step, so effort on unfinished episodes is charged); robot idle
time (the share of the robots' time spent waiting for the operator). Per size: the operator's
utilisation (busy time, delays included, over the run's time).

**Robots per operator** (``robots_per_operator``): the largest size run at which the fleet held its
clock, every task of the mix has a robot, every task succeeds in at least 95% of its episodes, the
queue wait's p95 is at most 100 ticks and no robot waited more than 300.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from unittest import mock

import httpx
import numpy as np
from sqlalchemy import select
from tqdm import tqdm

from bench.loop import launch_service, stop_service, wait_ready
from client.operator_bot import HumanPace, OperatorBot
from server.db import FINISHED, EpisodeRecord, SegmentRecord
from server.fleet.assistance import QUEUE_ORDERS
from server.settings import Settings
from sim.registry import TASKS

OPERATORS_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "operators.toml"
DEFAULT_MIX = {"lift-cube": 0.7, "lift-hammer": 0.1, "cup-stack": 0.1, "open-drawer": 0.1}
PRODUCT_HZ = 10.0  # the product's control rate (``Settings.control_hz``'s default); below it a run is "slowed"
KEEPS_CLOCK = 0.95  # a fleet that held less than this share of its control rate did not keep its clock
SUCCESS_MIN, WAIT_P95_MAX_TICKS, WAIT_MAX_TICKS = 0.95, 100, 300  # the headline's conditions


@dataclass(frozen=True)
class FleetMix:
    """Task -> share of the fleet; shares positive, summing to 1, tasks known to the simulator."""

    shares: dict[str, float]

    def __post_init__(self) -> None:
        if not self.shares:
            raise ValueError("the fleet mix is empty: give task=share items")
        for task, share in self.shares.items():
            if task not in TASKS:
                raise ValueError(f"unknown task {task!r} in the fleet mix: one of {', '.join(sorted(TASKS))}")
            if not (isinstance(share, int | float) and math.isfinite(share) and share > 0):
                raise ValueError(f"the share of {task} must be a positive number, got {share!r}")
        total = sum(self.shares.values())
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"the fleet mix's shares must sum to 1, got {total:.6g}")

    @classmethod
    def parse(cls, items: list[str] | None) -> FleetMix:
        """``["lift-cube=0.7", ...]`` (None: ``DEFAULT_MIX``)."""
        if not items:
            return cls(dict(DEFAULT_MIX))
        shares: dict[str, float] = {}
        for item in items:
            task, sep, share = item.partition("=")
            if not sep:
                raise ValueError(f"--mix takes task=share items, got {item!r}")
            if task in shares:
                raise ValueError(f"--mix names {task} twice")
            try:
                shares[task] = float(share)
            except ValueError:
                raise ValueError(f"the share of {task} must be a number, got {share!r}") from None
        return cls(shares)

    def counts(self, size: int) -> dict[str, int]:
        """Robots per task in a fleet of ``size`` (largest remainder; ties to the task named first); tasks
        whose share rounds to no robot are left out."""
        if size < 1:
            raise ValueError(f"a fleet needs at least one robot, got {size}")
        exact = {t: s * size for t, s in self.shares.items()}
        counts = {t: int(math.floor(x + 1e-9)) for t, x in exact.items()}
        order = sorted(self.shares, key=lambda t: -(exact[t] - counts[t]))  # stable: ties keep the given order
        for t in order[: size - sum(counts.values())]:
            counts[t] += 1
        return {t: n for t, n in counts.items() if n}


@dataclass(frozen=True)
class Pace:
    """A person's pace in control ticks (``client.operator_bot.HumanPace`` in seconds): claim, from a
    request at the head of the queue to the claim; switch, more when the robot is another than the one
    served last; min_takeover, the least time a takeover occupies the operator."""

    claim: int = 10
    switch: int = 20
    min_takeover: int = 20

    def __post_init__(self) -> None:
        for name in ("claim", "switch", "min_takeover"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"the {name} delay must be a whole number of ticks >= 0, got {v!r}")

    def seconds(self, hz: float) -> HumanPace:
        return HumanPace(self.claim / hz, self.switch / hz, self.min_takeover / hz)


@dataclass(frozen=True)
class OperatorsPlan:
    """sizes: fleet sizes, each run on a fresh service; ticks: the fleet's clock ticks each size runs;
    control_hz: the fleet's clock (None: the config's); order: the queue's order (``QUEUE_ORDERS``)."""

    sizes: tuple[int, ...]
    mix: FleetMix = field(default_factory=lambda: FleetMix(dict(DEFAULT_MIX)))
    ticks: int = 3000
    control_hz: float | None = None
    pace: Pace = field(default_factory=Pace)
    order: str = "priority"
    config: Path = OPERATORS_CONFIG
    overrides: dict[str, str] = field(default_factory=dict)  # HITL_* variables for the service

    def __post_init__(self) -> None:
        if not self.sizes or any(not isinstance(n, int) or n < 1 for n in self.sizes):
            raise ValueError(f"fleet sizes must be positive whole numbers, got {self.sizes!r}")
        if self.ticks < 1:
            raise ValueError(f"ticks must be positive, got {self.ticks}")
        if self.control_hz is not None and not (0 < self.control_hz <= 200):
            raise ValueError(f"control_hz must be in (0, 200], got {self.control_hz}")
        if self.order not in QUEUE_ORDERS:
            raise ValueError(f"unknown queue order {self.order!r}: one of {', '.join(QUEUE_ORDERS)}")
        if not Path(self.config).is_file():
            raise FileNotFoundError(f"config file {self.config} not found")


def _quantiles(waits_s: list[float], hz: float) -> dict:
    if not waits_s:
        return {"n": 0} | {f"{k}_{u}": None for k in ("p50", "p95", "max") for u in ("s", "ticks")}
    w = np.asarray(waits_s, dtype=np.float64)
    s = {"p50": float(np.quantile(w, 0.5)), "p95": float(np.quantile(w, 0.95)), "max": float(w.max())}
    return {"n": len(w)} | {f"{k}_s": v for k, v in s.items()} | {f"{k}_ticks": v * hz for k, v in s.items()}


def size_report(
    counts: dict[str, int],
    episodes: list[EpisodeRecord],
    segments: list[SegmentRecord],
    claims: list[tuple[int, float]],
    unclaimed: list[tuple[int, float]],
    task_of: dict[int, str],
    seconds: float,
    hz: float,
    busy_s: float,
) -> dict:
    """One size's figures from what its service recorded: ``claims`` (robot, seconds its request waited) and
    ``unclaimed`` (robot, age at the end) are the queue's; ``hz`` the clock the fleet held (ticks per second).

    Success counts the episodes that ended in the window; operator steps count every takeover opened in it
    (``segments``, each with the steps the operator drove), those of episodes still running at its end too,
    so ROHE (successes per operator step) charges the effort a fleet spent on episodes it did not finish."""
    per_task = {}
    for task, robots in counts.items():
        done = [e for e in episodes if e.task == task and e.outcome in FINISHED]
        ok = sum(e.outcome == "success" for e in done)
        steps = sum(g.steps for g in segments if g.task == task)
        waits = [w for r, w in claims if task_of.get(r) == task] + [w for r, w in unclaimed if task_of.get(r) == task]
        per_task[task] = {
            "robots": robots,
            "episodes": len(done),
            "successes": ok,
            "success_rate": ok / len(done) if done else None,
            "takeovers": sum(s.task == task for s in segments),
            "operator_steps": steps,
            "rohe": ok / steps if steps else None,
            "queue_wait": _quantiles(waits, hz),
            "unclaimed_at_end": sum(task_of.get(r) == task for r, _ in unclaimed),
            "robot_idle": sum(waits) / (robots * seconds),
        }
    all_waits = [w for _, w in claims] + [w for _, w in unclaimed]
    done = [e for e in episodes if e.outcome in FINISHED]
    ok = sum(e.outcome == "success" for e in done)
    steps = sum(g.steps for g in segments)
    return {
        "robots": sum(counts.values()),
        "counts": counts,
        "episodes": len(done),
        "success_rate": ok / len(done) if done else None,
        "operator_steps": steps,
        "rohe": ok / steps if steps else None,
        "queue_wait": _quantiles(all_waits, hz),
        "unclaimed_at_end": len(unclaimed),
        "utilisation": busy_s / seconds,
        "robot_idle": sum(all_waits) / (sum(counts.values()) * seconds),
        "per_task": per_task,
    }


def keeps_up(size: dict, tasks: list[str]) -> bool:
    """Whether one operator kept this fleet: the fleet held its clock, every task of the mix present and at
    >= 95% success (with an episode to show it), queue wait p95 <= 100 ticks and max <= 300 ticks."""
    if not size["clock"]["kept_clock"]:  # a fleet behind its clock makes the operator's delays look shorter
        return False
    per = size["per_task"]
    if any(t not in per or per[t]["success_rate"] is None or per[t]["success_rate"] < SUCCESS_MIN for t in tasks):
        return False
    w = size["queue_wait"]
    return w["n"] == 0 or (w["p95_ticks"] <= WAIT_P95_MAX_TICKS and w["max_ticks"] <= WAIT_MAX_TICKS)


def robots_per_operator(sizes: list[dict], tasks: list[str]) -> int | None:
    """The largest size run that one operator keeps (``keeps_up``); None when none does."""
    kept = [s["robots"] for s in sizes if keeps_up(s, tasks)]
    return max(kept, default=None)


def _utc(t: datetime) -> datetime:
    """A stored time as an aware UTC one (SQLite gives it back naive)."""
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def _ticks(url: str, token: str) -> int:
    with httpx.Client(base_url=url + "/api/v1", headers={"Authorization": f"Bearer {token}"}, timeout=10) as c:
        return int(c.get("/metrics/fleet").raise_for_status().json()["ticks"])


def _unclaimed(url: str, token: str) -> list[tuple[int, float]]:
    with httpx.Client(base_url=url + "/api/v1", headers={"Authorization": f"Bearer {token}"}, timeout=10) as c:
        return [
            (r["robot_id"], float(r["waiting_s"]))
            for r in c.get("/assistance").raise_for_status().json()
            if r["holder"] is None
        ]


def run_size(plan: OperatorsPlan, size: int, data_dir: Path, progress: bool = True) -> dict:
    """One fleet of ``size`` served by one operator for ``plan.ticks`` ticks; its ``size_report`` and clock."""
    counts = plan.mix.counts(size)
    policies = {g.task: g.policy for g in Settings.load(plan.config).robots if g.policy is not None}
    robots = [
        {"task": t, "count": n} | ({"policy": str(policies[t])} if t in policies else {}) for t, n in counts.items()
    ]
    env = dict(plan.overrides) | {
        "HITL_DATA_DIR": str(data_dir),
        "HITL_ROBOTS": json.dumps(robots),
        "HITL_QUEUE__ORDER": plan.order,
    }
    if plan.control_hz is not None:
        env["HITL_CONTROL_HZ"] = str(plan.control_hz)
    with mock.patch.dict(os.environ, env):  # the settings the service reads, its --set overrides included
        settings = Settings.load(plan.config)
    hz = settings.control_hz
    if not hz:
        raise ValueError("the operators benchmark needs a fleet clock: control_hz > 0")
    since = datetime.now(UTC)
    proc, url, sessions, token = launch_service(plan.config, settings, env)
    bot = OperatorBot(url, token, pace=plan.pace.seconds(hz))
    stop = threading.Event()
    thread = threading.Thread(target=bot.run, kwargs={"stop": stop.is_set, "idle_sleep": 0.05}, daemon=True)
    seconds = plan.ticks / hz
    try:
        wait_ready(url, proc, timeout=300)
        ticks0, started = _ticks(url, token), time.monotonic()
        thread.start()
        with tqdm(total=int(seconds), desc=f"{size} robots", unit="s", disable=not progress) as bar:
            while (elapsed := time.monotonic() - started) < seconds:
                if proc.poll() is not None:
                    raise RuntimeError(f"hitl serve exited with code {proc.returncode} during the run")
                time.sleep(min(1.0, seconds - elapsed))
                bar.n = int(time.monotonic() - started)
                bar.refresh()
        # the window ends: what the queue, the operator and the clock show now is the run's
        end, until = time.monotonic(), datetime.now(UTC)
        claims, busy = list(bot.waits), bot.busy_at(end)
        unclaimed = _unclaimed(url, token)
        ticks1, wall = _ticks(url, token), end - started
        stop.set()
        thread.join(timeout=60)
    finally:
        stop.set()
        stop_service(proc)
        bot.close()
    with sessions() as s:
        started_in = select(EpisodeRecord).where(EpisodeRecord.started_at >= since)
        episodes = [e for e in s.scalars(started_in) if e.ended_at is not None and _utc(e.ended_at) <= until]
        opened = select(SegmentRecord).where(SegmentRecord.started_at >= since)
        segments = [g for g in s.scalars(opened) if _utc(g.started_at) <= until]
        task_of = {r.robot_id: r.task for r in s.scalars(started_in)}
    held = (ticks1 - ticks0) / wall
    out = size_report(counts, episodes, segments, claims, unclaimed, task_of, wall, held, busy)
    out["clock"] = {
        "control_hz": hz,
        "slowed": hz < PRODUCT_HZ,
        "held_hz": held,
        "kept_clock": held >= KEEPS_CLOCK * hz,
        "seconds": wall,
        "ticks": ticks1 - ticks0,
    }
    out["operator"] = {"claims": len(claims), "commands": bot.commands, "errors": bot.errors, "busy_s": busy}
    return out


def run_operators(plan: OperatorsPlan, data_root: Path | None = None, progress: bool = True) -> dict:
    """Every size of ``plan``, each on a fresh service under ``data_root`` (default: a temporary folder)."""
    root = Path(tempfile.mkdtemp(prefix="hitl-operators-")) if data_root is None else Path(data_root)
    sizes = [run_size(plan, n, root / f"{plan.order}-{n}", progress) for n in plan.sizes]
    tasks = list(plan.mix.shares)
    return {
        "plan": {
            "sizes": list(plan.sizes),
            "mix": plan.mix.shares,
            "ticks": plan.ticks,
            "control_hz": plan.control_hz,
            "pace_ticks": asdict(plan.pace),
            "order": plan.order,
            "config": plan.config.name,
            "overrides": plan.overrides,
        },
        "criteria": {
            "success_min": SUCCESS_MIN,
            "wait_p95_ticks": WAIT_P95_MAX_TICKS,
            "wait_max_ticks": WAIT_MAX_TICKS,
        },
        "robots_per_operator": robots_per_operator(sizes, tasks),
        "sizes": sizes,
    }

"""``hitl bench nights``: does the fleet need less help every night? Days and nights of the real service.

A real ``hitl serve`` process runs a configured fleet (``configs/nights.toml`` by default) with the
simulated operator (``OperatorBot``, the REST API only) answering every request, as in ``hitl bench
loop``. A day lasts ``day_minutes``, or until every task has finished ``day_episodes`` episodes that
started that day. Then the night:

1. the operator goes home and an admin pauses every robot (``POST /robots/{id}/pause``): the job has
   the machine, as a lab's fleet stands still overnight;
2. the benchmark moves the service's clock (``[finetune] clock_file``, ``server.finetune.scheduler.FileClock``)
   to the schedule's next due time, and the service's own scheduler starts the nightly job: the
   benchmark never starts it itself. The job fine-tunes every lineage with new takeovers, recalibrates,
   evaluates on its held-out seeds and applies its gate (``server.finetune.job``);
3. once the job's process has ended (``GET /finetune-schedule``), the morning: a robot not yet on its
   lineage's active version is reset until the fleet has loaded it (the hot swap moves a robot at its
   next episode); the day then resets every robot, so each starts afresh on what the registry serves,
   and the operator comes back.

Reported from the service's own database, per day and per task: episodes (those that started that
day and ended on their own), autonomous success (episodes that asked nothing and succeeded), success
with help, requests, assisted steps and operator time per episode, requests per policy step (on the
training task, every request is a false alarm), and the policy versions served. Per night: the job's
exit code and time, and each lineage's job: its data counts, the gate's evidence and decision, and the
version it made. ``goals`` compares the days on the shifted lift tasks.
"""

from __future__ import annotations

import json
import os
import platform
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
from sqlalchemy import or_, select
from tqdm import tqdm

from bench.loop import launch_service, stop_service, wait_ready
from client.operator_bot import OperatorBot
from server.auth import create_token
from server.db import FINISHED, EpisodeRecord, FinetuneJob, PolicyVersion, SegmentRecord
from server.finetune.scheduler import next_due, write_clock
from server.settings import Settings

NIGHTS_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "nights.toml"
FIRST_MORNING = datetime(2027, 1, 4, 8, 0)  # day 1 on the service's clock (local time); any date would do
SHIFTED_LIFT = ("lift-nut", "lift-hammer", "lift-hook")
TRAINING_TASK = "lift-cube"


@dataclass(frozen=True)
class NightsPlan:
    """days: at least 2 (one night); a day ends after ``day_minutes`` or once every task has finished
    ``day_episodes`` episodes, whichever comes first (one of them must be set); night_timeout_s: the
    longest a night's job may take before the run stops with what it has (3 hours: on a fresh clone the
    first night also records every lineage's pretraining data, 56 minutes on an idle 2-core machine, and
    a job that shares the machine runs at idle priority)."""

    config: Path = NIGHTS_CONFIG
    days: int = 3
    day_minutes: float | None = 12.0
    day_episodes: int | None = None
    night_timeout_s: float = 3 * 3600.0
    data_dir: Path | None = None
    env: dict[str, str] = field(default_factory=dict)
    progress: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.days, int) and self.days >= 2):
            raise ValueError(f"--days must be an integer >= 2 (a day, a night, a day), got {self.days!r}")
        if self.day_minutes is None and self.day_episodes is None:
            raise ValueError("a day needs an end: --day-minutes, --day-episodes or both")
        if self.day_minutes is not None and not self.day_minutes > 0:
            raise ValueError(f"--day-minutes must be positive, got {self.day_minutes!r}")
        if self.day_episodes is not None and not (isinstance(self.day_episodes, int) and self.day_episodes >= 1):
            raise ValueError(f"--day-episodes must be an integer >= 1, got {self.day_episodes!r}")
        if not self.night_timeout_s > 0:
            raise ValueError(f"--night-timeout must be positive, got {self.night_timeout_s!r}")


@dataclass
class Window:
    """One day or night in real time (UTC, as the database records), and on the service's clock."""

    started: datetime
    ended: datetime | None = None
    clock: datetime | None = None
    bot: dict | None = None  # the operator's takeovers, commands and errors that day


class Service:
    """The running ``hitl serve`` of a run: its REST API as admin and as the operator bot."""

    def __init__(self, plan: NightsPlan, data_dir: Path) -> None:
        self.plan, self.data_dir = plan, data_dir
        data_dir.mkdir(parents=True, exist_ok=True)
        self.clock_file = data_dir / "clock.txt"
        write_clock(self.clock_file, FIRST_MORNING)
        base = Settings.load(plan.config, data_dir=data_dir)
        finetune = base.finetune.model_dump(mode="json") | {"clock_file": str(self.clock_file)}
        if not base.finetune.schedule:
            raise ValueError(f"{plan.config}: [finetune] schedule is empty: the night's job would never start")
        self.schedule = base.finetune.schedule
        env = {"HITL_DATA_DIR": str(data_dir), "HITL_FINETUNE": json.dumps(finetune), **plan.env}
        self.settings = Settings.load(plan.config, data_dir=data_dir, finetune=finetune)
        self.proc, self.url, self.sessions, self.operator_token = launch_service(plan.config, self.settings, env)
        admin = create_token(self.sessions, f"bench-nights-admin-{time.time_ns()}", "admin")
        self.api = httpx.Client(base_url=self.url + "/api/v1", headers={"Authorization": f"Bearer {admin}"}, timeout=30)
        self.clock = FIRST_MORNING

    def wait_ready(self) -> None:
        wait_ready(self.url, self.proc, timeout=600)

    def robots(self) -> list[dict]:
        return self.api.get("/robots").raise_for_status().json()

    def each_robot(self, action: str) -> None:
        """pause or reset every robot (a faulted one is left as it is: it restarts by itself)."""
        for robot in self.robots():
            r = self.api.post(f"/robots/{robot['id']}/{action}")
            if r.status_code not in (200, 409):
                r.raise_for_status()

    def schedule_state(self) -> dict:
        return self.api.get("/finetune-schedule").raise_for_status().json()

    def set_clock(self, when: datetime) -> None:
        self.clock = when
        write_clock(self.clock_file, when)

    def stop(self) -> None:
        self.api.close()
        stop_service(self.proc, timeout=120)


def run_nights(plan: NightsPlan, on_progress: Callable[[dict], None] | None = None) -> dict:
    """Runs ``plan.days`` days with a night between each two; returns the report (``nights_report``).
    ``on_progress`` gets the report so far (``complete`` false) after every day and night, so that a run
    stopped partway (a machine lent for less time than the run takes) still leaves what it measured."""
    data_dir = Path(plan.data_dir) if plan.data_dir is not None else _temp_dir()
    if (data_dir / "hitl.db").exists():
        raise ValueError(f"{data_dir} already holds a service database: a run starts from the bundled policies")
    service = Service(plan, data_dir)
    days: list[Window] = []
    nights: list[dict] = []
    try:
        service.wait_ready()
        for day in range(1, plan.days + 1):
            if day > 1:
                nights.append(_night(service, plan, day - 1))
                if on_progress is not None:
                    on_progress(nights_report(service.sessions, service.settings, plan, days, nights, complete=False))
                if nights[-1]["exit_code"] is None:  # the job never ended: the run stops with what it has
                    break
                _morning(service, FIRST_MORNING + timedelta(days=day - 1))
            days.append(_day(service, plan, day))
            if on_progress is not None:
                on_progress(nights_report(service.sessions, service.settings, plan, days, nights, complete=False))
    finally:
        service.stop()
    # complete only when every planned day ran: a night whose job never ended stops the run short
    return nights_report(service.sessions, service.settings, plan, days, nights, complete=len(days) == plan.days)


def _temp_dir() -> Path:
    import tempfile

    return Path(tempfile.mkdtemp(prefix="hitl-nights-"))


def _day(service: Service, plan: NightsPlan, day: int) -> Window:
    """Every robot starts a fresh episode, on its lineage's active version; the operator serves the
    queue until the day's end; the robots are paused at its end."""
    window = Window(datetime.now(UTC), clock=service.clock)
    service.each_robot("reset")  # also ends a pause; an episode from before the day is not counted
    bot = OperatorBot(service.url, service.operator_token)
    stop = threading.Event()
    thread = threading.Thread(target=bot.run, kwargs={"stop": stop.is_set}, daemon=True)
    thread.start()
    started = time.monotonic()
    limit = plan.day_minutes * 60 if plan.day_minutes is not None else float("inf")
    tasks = sorted({g.task for g in service.settings.robots})
    desc = f"day {day}"
    with tqdm(
        total=None if plan.day_minutes is None else int(limit), desc=desc, unit="s", disable=not plan.progress
    ) as bar:
        while (elapsed := time.monotonic() - started) < limit:
            time.sleep(min(2.0, max(0.1, limit - elapsed)))
            bar.n = int(time.monotonic() - started)
            if plan.day_episodes is not None:
                done = _finished_per_task(service.sessions, window.started)
                bar.set_postfix_str(" ".join(f"{t}:{done.get(t, 0)}" for t in tasks), refresh=False)
                if all(done.get(t, 0) >= plan.day_episodes for t in tasks):
                    break
            bar.refresh()
    stop.set()
    thread.join(timeout=120)
    bot.close()
    service.each_robot("pause")
    window.ended = datetime.now(UTC)
    window.bot = {"takeovers": bot.takeovers, "commands": bot.commands, "errors": bot.errors}
    return window


def _finished_per_task(sessions, since: datetime) -> dict[str, int]:
    with sessions() as s:
        rows = s.execute(
            select(EpisodeRecord.task, EpisodeRecord.outcome).where(EpisodeRecord.started_at >= since)
        ).all()
    out: dict[str, int] = defaultdict(int)
    for task, outcome in rows:
        out[task] += int(outcome in FINISHED)
    return out


def _night(service: Service, plan: NightsPlan, night: int) -> dict:
    """Moves the service's clock to the schedule's next due time and waits for the job it starts."""
    before = service.schedule_state()
    started = datetime.now(UTC)
    due = next_due(service.schedule, service.clock)
    service.set_clock(due)
    t0 = time.monotonic()
    state = before
    with tqdm(desc=f"night {night}", unit="s", disable=not plan.progress) as bar:
        while time.monotonic() - t0 < plan.night_timeout_s:
            time.sleep(2.0)
            state = service.schedule_state()
            bar.n = int(time.monotonic() - t0)
            bar.set_postfix_str(_night_progress(service.sessions, started), refresh=False)
            bar.refresh()
            if state["launches"] > before["launches"] and state["last_exit_code"] is not None:
                break
            if state["launches"] == before["launches"] and time.monotonic() - t0 > 60:
                raise RuntimeError(f"night {night}: the service's scheduler started no job within 60 s of {due}")
    ended = datetime.now(UTC)
    done = state["launches"] > before["launches"] and state["last_exit_code"] is not None
    return {
        "night": night,
        "clock": due.isoformat(),
        "seconds": round((ended - started).total_seconds(), 1),
        "exit_code": state["last_exit_code"] if done else None,
        "timed_out": not done,
        "jobs": _jobs(service.sessions, started),
    }


def _portable_text(text: str | None) -> str | None:
    """A message with the data root's folder left out of its paths (a report names no machine's folders)."""
    from storage.paths import data_root

    return None if text is None else text.replace(str(data_root()) + "/", "")


def _night_progress(sessions, since: datetime) -> str:
    with sessions() as s:
        rows = s.scalars(select(FinetuneJob).where(FinetuneJob.created_at >= since).order_by(FinetuneJob.id)).all()
        return " ".join(f"{j.lineage}:{j.stage or j.status} {j.progress:.0%}" for j in rows)


def _morning(service: Service, clock: datetime) -> None:
    """Every robot moved onto its lineage's active version: a robot still on another one is reset
    (again, until the fleet has loaded the new version). A reset ends the episode the night paused
    (outcome ``reset``: not counted); the day then starts every robot afresh (``_day``)."""
    service.set_clock(clock)
    deadline = time.monotonic() + 300
    while (stale := _robots_off_active(service)) and time.monotonic() < deadline:
        for robot_id in stale:
            r = service.api.post(f"/robots/{robot_id}/reset")
            if r.status_code not in (200, 409):
                r.raise_for_status()
        time.sleep(2.0)
    if stale:
        raise RuntimeError(f"robots {stale} are still not on their lineage's active version after 5 minutes")


def _robots_off_active(service: Service) -> list[int]:
    """Robots whose version is not their lineage's active one."""
    rows = service.api.get("/policies").raise_for_status().json()
    active = {r["name"]: r for r in rows if r["status"] == "active"}
    off = []
    for r in rows:
        if r["status"] != "active" and r["name"] in active:
            off += r["robots"]
    return sorted(off)


def _jobs(sessions, since: datetime) -> list[dict]:
    """The night's jobs, one per lineage: data counts, the gate's evidence and decision, the version."""
    with sessions() as s:
        # a job resumed tonight was created on an earlier night
        tonight = or_(FinetuneJob.created_at >= since, FinetuneJob.ended_at >= since)
        rows = list(s.scalars(select(FinetuneJob).where(tonight).order_by(FinetuneJob.id)))
        refs = {v.id: v.ref for v in s.scalars(select(PolicyVersion))}
    out = []
    for j in rows:
        data = j.data or {}
        out.append(
            {
                "job": j.id,
                "lineage": j.lineage,
                "status": j.status,
                "trigger": j.trigger,
                "resumes": data.get("resumes", 0),
                "error": _portable_text(j.error),
                "parent": refs.get(j.parent_id),
                "version": refs.get(j.version_id),
                "promoted": (j.gate or {}).get("promoted", False),
                "gate": {k: (j.gate or {}).get(k) for k in ("promote", "reason", "evidence")},
                "data": data.get("counts", {}),
                "tasks": data.get("tasks", []),
                "evaluation": j.evaluation or {},
                "seconds": round((j.ended_at - j.started_at).total_seconds(), 1)
                if j.ended_at and j.started_at
                else None,
            }
        )
    return out


def nights_report(
    sessions, settings: Settings, plan: NightsPlan, days: list[Window], nights: list[dict], complete: bool = True
) -> dict:
    """What the database holds of each day, per task, and each night's jobs; ``goals`` on the shifted lift
    tasks; ``complete``: false for the report of a run still under way (``run_nights``'s ``on_progress``) or
    stopped short by a night whose job never ended."""
    with sessions() as s:
        episodes = list(s.scalars(select(EpisodeRecord)))
        segments = list(s.scalars(select(SegmentRecord)))
        refs = {v.id: v.ref for v in s.scalars(select(PolicyVersion))}
    operator_s: dict[int, float] = defaultdict(float)
    causes: dict[int, list[str]] = defaultdict(list)  # episode id -> what made it ask, per takeover
    for seg in segments:
        if seg.episode_id is not None and seg.ended_at is not None:
            operator_s[seg.episode_id] += (seg.ended_at - seg.started_at).total_seconds()
        if seg.episode_id is not None:
            causes[seg.episode_id].append(_cause(seg.reason))
    day_docs = []
    for n, w in enumerate(days, start=1):
        mine = [e for e in episodes if e.started_at >= w.started and (w.ended is None or e.started_at < w.ended)]
        per_task = {}
        for task in sorted({g.task for g in settings.robots}):
            per_task[task] = _task_day([e for e in mine if e.task == task], operator_s, refs, causes)
        day_docs.append(
            {
                "day": n,
                "clock": w.clock.isoformat() if w.clock else None,
                "minutes": round(((w.ended or datetime.now(UTC)) - w.started).total_seconds() / 60, 2),
                "bot": w.bot,
                "per_task": per_task,
                "shifted_lift": _task_day([e for e in mine if e.task in SHIFTED_LIFT], operator_s, refs, causes),
            }
        )
    return {
        "complete": complete,
        "date": datetime.now(UTC).date().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
        "config": _config_name(plan.config),
        "plan": {k: v for k, v in asdict(plan).items() if k not in ("config", "data_dir", "progress")},
        "robots": {g.task: g.count for g in settings.robots},
        "schedule": settings.finetune.schedule,
        "finetune": settings.finetune.model_dump(mode="json", exclude={"clock_file"}),
        "days": day_docs,
        "nights": nights,
        "goals": goals(day_docs),
    }


def _config_name(path: Path) -> str:
    from storage.paths import portable

    return portable(path)


def _cause(reason: str | None) -> str:
    """What made a robot ask, from its request's reason (``server.fleet.loop``): ``watchdog``, or the
    asking signal's name."""
    head = (reason or "").split(":", 1)[0].strip()
    return head or "unknown"


def _task_day(
    episodes: list[EpisodeRecord], operator_s: dict[int, float], refs: dict[int, str], causes: dict[int, list[str]]
) -> dict:
    """One task's day; ``takeovers_by_cause``: what made the robots ask (the first takeover of each episode
    that asked: the watchdog, or the signal); ``assisted_steps_per_helped_episode``: the operator's steps
    in an episode that asked (what a request costs, where ``assisted_steps_per_episode`` also counts the
    episodes that asked nothing)."""
    done = [e for e in episodes if e.outcome in FINISHED]
    n = len(done)
    steps = sum(e.steps for e in done)
    versions: dict[str, int] = defaultdict(int)
    first_cause: dict[str, int] = defaultdict(int)
    helped = [e for e in done if e.assistance_events > 0]
    for e in done:
        versions[refs.get(e.policy_id, "?")] += 1
        if causes.get(e.id):
            first_cause[causes[e.id][0]] += 1

    def per(x: float) -> float | None:
        return round(x / n, 3) if n else None

    return {
        "episodes": n,
        "autonomous_success": per(sum(e.outcome == "success" and e.assistance_events == 0 for e in done)),
        "success_with_help": per(sum(e.outcome == "success" for e in done)),
        "requests_per_episode": per(sum(e.assistance_events for e in done)),
        "assisted_steps_per_episode": per(sum(e.assisted_steps for e in done)),
        "operator_seconds_per_episode": per(sum(operator_s.get(e.id, 0.0) for e in done)),
        "requests_per_step": round(sum(e.assistance_events for e in done) / steps, 4) if steps else None,
        "versions": dict(sorted(versions.items())),
        "takeovers_by_cause": dict(sorted(first_cause.items())),
        "assisted_steps_per_helped_episode": round(sum(e.assisted_steps for e in helped) / len(helped), 3)
        if helped
        else None,
    }


def goals(days: list[dict]) -> dict:
    """The issue's goals, from the days: on the shifted lift tasks, assisted steps per episode after the
    first night at most half of day 1's, and autonomous success up by at least 0.4; lift-cube's
    autonomous success at least 0.95 every day. None where a day has no episode of those tasks."""
    first, later = days[0], days[1:]
    d1 = first["shifted_lift"]
    out: dict = {
        "shifted_lift_day1": {k: d1[k] for k in ("episodes", "assisted_steps_per_episode", "autonomous_success")}
    }
    for d in later:
        s = d["shifted_lift"]
        ratio = (
            s["assisted_steps_per_episode"] / d1["assisted_steps_per_episode"]
            if s["assisted_steps_per_episode"] is not None and d1["assisted_steps_per_episode"]
            else None
        )
        gain = (
            s["autonomous_success"] - d1["autonomous_success"]
            if s["autonomous_success"] is not None and d1["autonomous_success"] is not None
            else None
        )
        out[f"day{d['day']}"] = {
            "assisted_steps_ratio": None if ratio is None else round(ratio, 3),
            "assisted_steps_halved": None if ratio is None else ratio <= 0.5,
            "autonomous_success_gain": None if gain is None else round(gain, 3),
            "autonomous_success_up_0_4": None if gain is None else gain >= 0.4,
        }
    cube = [d["per_task"].get(TRAINING_TASK, {}).get("autonomous_success") for d in days]
    out["lift_cube_autonomous_success"] = cube
    out["lift_cube_at_least_0_95"] = None if any(c is None for c in cube) else all(c >= 0.95 for c in cube)
    return out

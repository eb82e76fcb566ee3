"""``hitl bench loop``: does the human-in-the-loop loop close? The demo fleet served by a real
``hitl serve`` process (a config file, ``configs/demo.toml`` by default, with the hand-back mode and
any settings overridden through ``HITL_*`` variables), the simulated operator (``OperatorBot``, the
REST API only) serving its queue from this process, for a wall-clock duration. Reported from the
service's own database: episodes that ended on their own (success or timeout) and their success
rate, overall and per task; assistance events, assisted steps and takeovers per task; episodes
interrupted; the bot's takeovers, commands and errors. Whether the queue served every robot is read
from the service before it stops (``queue_snapshot``): the longest wait from a request to its claim
(the queue's own count, ``/metrics/fleet``), and each request still unclaimed at the end with its age
so far, since a robot that was never served has no claim to show its wait. Per task, the longest
wait among the bot's claims (the wait the service answered each claim with; the bot is the run's
only operator).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from datetime import UTC, datetime
from pathlib import Path

import httpx
from sqlalchemy import select
from tqdm import tqdm

from client.operator_bot import OperatorBot
from server.auth import create_token
from server.db import FINISHED, EpisodeRecord, SegmentRecord, make_engine, migrate, session_factory
from server.settings import Settings

DEMO_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "demo.toml"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, proc: subprocess.Popen, timeout: float) -> None:
    """Waits until the service ``proc`` started answers ``/readyz`` at ``url`` (RuntimeError if it exits
    first or is not ready after ``timeout`` seconds)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"hitl serve exited with code {proc.returncode} before it was ready")
        try:
            if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"the service was not ready after {timeout:.0f} s")


def stop_service(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Stops a service ``launch_service`` started: SIGTERM (it closes open takeovers and episodes), then
    SIGKILL if it has not exited within ``timeout`` seconds."""
    proc.terminate()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()


def launch_service(config: Path, settings: Settings, env: dict[str, str] | None = None):
    """Prepares ``settings``' database and an operator token for the bot, then starts
    ``hitl serve --config config`` on a free 127.0.0.1 port with ``env`` on top of this process's
    environment. Returns (process, url, sessions, token); the service is not ready yet (``wait_ready``)."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    token = create_token(sessions, f"bench-bot-{time.time_ns()}", "operator")
    port = _free_port()
    cmd = [sys.executable, "-m", "hitl.cli", "serve", "--config", str(config), "--port", str(port)]
    proc = subprocess.Popen(cmd, env=os.environ | (env or {}), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return proc, f"http://127.0.0.1:{port}", sessions, token


def run_loop(
    seconds: float,
    mode: str = "continuous",
    config: Path | None = None,
    data_dir: Path | None = None,
    env: dict[str, str] | None = None,
    bot: bool = True,
    progress: bool = True,
) -> dict:
    """Serves ``config`` with ``hand_back = mode`` for ``seconds`` (after readiness) with the operator
    bot helping (``bot``), then stops the service with SIGTERM and reports what its database holds."""
    config = Path(config) if config is not None else DEMO_CONFIG
    data_dir = Path(tempfile.mkdtemp(prefix="hitl-loop-")) if data_dir is None else Path(data_dir)
    overrides = {"HITL_DATA_DIR": str(data_dir), "HITL_CONTROLLER__HAND_BACK": mode, **(env or {})}
    settings = Settings.load(config, data_dir=data_dir, controller={"hand_back": mode})
    since = datetime.now(UTC)  # only this run's episodes and takeovers are reported (the folder may be reused)
    proc, url, sessions, token = launch_service(config, settings, overrides)
    operator = OperatorBot(url, token) if bot else None
    stop = threading.Event()
    try:
        wait_ready(url, proc, timeout=300)
        started = time.monotonic()
        thread = None
        if operator is not None:
            thread = threading.Thread(target=operator.run, kwargs={"stop": stop.is_set}, daemon=True)
            thread.start()
        with tqdm(total=int(seconds), desc=f"loop ({mode})", unit="s", disable=not progress) as bar:
            while (elapsed := time.monotonic() - started) < seconds:
                time.sleep(min(1.0, seconds - elapsed))
                bar.n = int(time.monotonic() - started)
                bar.refresh()
        stop.set()
        if thread is not None:
            thread.join(timeout=30)
        queue = queue_snapshot(url, token)
    finally:
        stop.set()
        stop_service(proc)
        if operator is not None:
            operator.close()
    return loop_report(sessions, settings, seconds, mode, operator, since, queue)


def queue_snapshot(url: str, token: str) -> dict | None:
    """The service's queue before it stops: ``longest_wait_s`` (request to claim, the longest so far)
    and ``unclaimed`` (robot, task, reason and age of each request nobody claimed, oldest first); None
    when the service does not answer."""
    try:
        with httpx.Client(base_url=url + "/api/v1", headers={"Authorization": f"Bearer {token}"}, timeout=10) as c:
            metrics = c.get("/metrics/fleet").raise_for_status().json()
            requests = c.get("/assistance").raise_for_status().json()
            tasks = {r["id"]: r["task"] for r in c.get("/robots").raise_for_status().json()}
    except httpx.HTTPError:
        return None
    unclaimed = [
        {"robot_id": r["robot_id"], "task": tasks.get(r["robot_id"]), "waited_s": r["waiting_s"], "reason": r["reason"]}
        for r in requests
        if r["holder"] is None
    ]
    unclaimed.sort(key=lambda r: -r["waited_s"])
    return {"longest_wait_s": metrics["queue_wait_max_s"], "unclaimed": unclaimed}


def loop_report(
    sessions,
    settings: Settings,
    seconds: float,
    mode: str,
    bot: OperatorBot | None,
    since: datetime | None = None,
    queue: dict | None = None,
) -> dict:
    """What the database holds of the run (episodes started ``since``): episodes that ended on their own,
    per task, and the takeovers; with ``queue`` (``queue_snapshot``), the longest wait and the requests
    left unclaimed."""
    since = since or datetime.min.replace(tzinfo=UTC)
    with sessions() as s:
        episodes = list(s.scalars(select(EpisodeRecord).where(EpisodeRecord.started_at >= since)))
        segments = list(s.scalars(select(SegmentRecord).where(SegmentRecord.started_at >= since)))
    keys = ("episodes", "successes", "events", "assisted_steps", "unassisted_episodes", "unassisted_successes")
    per_task: dict[str, dict] = defaultdict(lambda: dict.fromkeys(keys, 0))
    for e in episodes:
        if e.outcome not in FINISHED:
            continue
        t = per_task[e.task]
        t["episodes"] += 1
        t["successes"] += int(e.outcome == "success")
        t["events"] += e.assistance_events
        t["assisted_steps"] += e.assisted_steps
        if e.assistance_events == 0:  # the policy alone: what the signal let go
            t["unassisted_episodes"] += 1
            t["unassisted_successes"] += int(e.outcome == "success")
    ended_by: dict[str, int] = defaultdict(int)
    asked_by: dict[str, int] = defaultdict(int)  # "watchdog" or the asking signal's name
    task_asked_by: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for seg in segments:
        ended_by[seg.ended_by or "open"] += 1
        who = seg.reason.split(":")[0].split(" ")[0]
        asked_by[who] += 1
        task_asked_by[seg.task][who] += 1
    task_of = {r.robot_id: r.task for r in [*episodes, *segments]}
    for robot_id, waited in bot.waits if bot is not None else ():
        t = per_task[task_of.get(robot_id, "?")]
        t["longest_wait_s"] = max(t.get("longest_wait_s") or 0.0, waited)
    for task, t in per_task.items():
        t.setdefault("longest_wait_s", None)
        t["success_rate"] = t["successes"] / t["episodes"] if t["episodes"] else None
        t["takeovers"] = sum(task_asked_by[task].values())
        t["takeovers_asked_by"] = dict(task_asked_by[task])
    n = sum(t["episodes"] for t in per_task.values())
    ok = sum(t["successes"] for t in per_task.values())
    return {
        "mode": mode,
        "seconds": seconds,
        "robots": sum(g.count for g in settings.robots),
        "episodes": n,
        "successes": ok,
        "success_rate": ok / n if n else None,
        "interrupted": sum(e.outcome not in FINISHED for e in episodes),
        "per_task": dict(sorted(per_task.items())),
        "takeovers_ended_by": dict(ended_by),
        "takeovers_asked_by": dict(asked_by),
        "longest_wait_s": None if queue is None else queue["longest_wait_s"],
        "unclaimed_at_end": None if queue is None else queue["unclaimed"],
        "bot": None if bot is None else {"takeovers": bot.takeovers, "commands": bot.commands, "errors": bot.errors},
    }

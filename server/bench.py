"""``hitl bench fleet``: the fleet runtime against the raw physics it runs on.

For each fleet size N, measured in the same run:

- raw: N bare worker processes stepping their task with hold actions as fast as they can (the
  physics limit of this machine);
- fleet: the fleet runtime free-running (no control-rate sleep), with one robot under teleop
  receiving a command every tick from another thread: ticks/s, tick period p50/p99, total env
  steps/s and command-to-applied latency p50/p99 (from the command's arrival at the fleet to the
  tick that sends it to the worker);
- the fleet's share of the raw throughput.

The policy and uncertainty are the real ones (the bundled policy of each task).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from server.assistance import QueueError
from server.db import make_engine, migrate, session_factory
from server.fleet import Fleet, FleetError
from server.settings import RobotGroup, Settings
from sim.spaces import TeleopCommand


def _raw_worker(task_name: str, seconds: float, start, out) -> None:
    from sim.registry import make_task

    task = make_task(task_name)
    task.reset(0)
    task.step(task.hold_action())  # compile / warm up before the clock starts
    start.wait()
    n, t_end = 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        r = task.step(task.hold_action())
        n += 1
        if r.done:
            task.reset(n)
    out.put(n)
    task.close()


def raw_throughput(task: str, n: int, seconds: float) -> float:
    """Total env steps/s of ``n`` bare processes stepping in parallel."""
    ctx = mp.get_context("spawn")
    start, out = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_raw_worker, args=(task, seconds, start, out), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    time.sleep(min(60.0, 3.0 + 1.5 * n))  # let every process build its simulator
    start.set()
    total = sum(out.get(timeout=seconds + 120) for _ in procs)
    for p in procs:
        p.join(timeout=30)
    return total / seconds


def fleet_throughput(task: str, n: int, seconds: float, data_dir: Path, torch_threads: int = 1) -> dict:
    settings = Settings(
        data_dir=data_dir,
        control_hz=0,
        robots=[RobotGroup(task=task, count=n)],
        lease_seconds=3600,
        torch_threads=torch_threads,
    )
    migrate(settings.db_url)
    fleet = Fleet(settings, session_factory(make_engine(settings.db_url)))
    fleet.start()
    stop = threading.Event()
    try:
        deadline = time.monotonic() + 120
        while any(r.frame is None for r in fleet.robots.values()) and time.monotonic() < deadline:
            time.sleep(0.2)
        with fleet.lock:  # robot 0 asks for help and a bench operator drives it
            r0 = fleet.robots[0]
            r0.mode, r0.hold_target = "waiting", r0.frame["hold"].copy()
            fleet.queue.open(0, 1.0, 1.0, "benchmark")
        fleet.claim(0, "bench")
        fleet.robots[0].teleop_left = None  # continuous for the whole measurement

        def operator() -> None:
            while not stop.is_set():
                with contextlib.suppress(QueueError, FleetError):  # the robot may be between episodes
                    fleet.command(0, "bench", TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), -1.0))
                time.sleep(0.005)

        threading.Thread(target=operator, daemon=True).start()
        time.sleep(1.0)
        with fleet.lock:
            steps0 = fleet.env_steps
            ticks0 = fleet.ticks
            fleet.tick_periods.clear()
            fleet.robots[0].latencies.clear()
        time.sleep(seconds)
        with fleet.lock:
            steps = fleet.env_steps - steps0
            ticks = fleet.ticks - ticks0
            periods = np.array(fleet.tick_periods)
            lat = np.array(fleet.robots[0].latencies)
    finally:
        stop.set()
        fleet.stop()
    return {
        "ticks_per_s": ticks / seconds,
        "tick_period_p50_ms": float(np.quantile(periods, 0.5) * 1e3) if len(periods) else None,
        "tick_period_p99_ms": float(np.quantile(periods, 0.99) * 1e3) if len(periods) else None,
        "env_steps_per_s": steps / seconds,
        "command_latency_p50_ms": float(np.quantile(lat, 0.5) * 1e3) if len(lat) else None,
        "command_latency_p99_ms": float(np.quantile(lat, 0.99) * 1e3) if len(lat) else None,
        "commands_applied": int(len(lat)),
        # target: command-to-applied p99 within one control period (here the median tick) + 20 ms
        "latency_target_ms": float(np.quantile(periods, 0.5) * 1e3 + 20) if len(periods) else None,
    }


def bench_fleet(
    task: str, sizes: list[int], seconds: float = 10.0, progress: bool = True, torch_threads: int = 1
) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in tqdm(sizes, desc="bench fleet", disable=not progress):
            raw = raw_throughput(task, n, seconds)
            fleet = fleet_throughput(task, n, seconds, Path(tmp) / f"n{n}", torch_threads)
            rows.append(
                {"robots": n, "raw_env_steps_per_s": raw, **fleet, "share_of_raw": fleet["env_steps_per_s"] / raw}
            )
    return {
        "benchmark": "fleet",
        "task": task,
        "seconds_per_measurement": seconds,
        "server_torch_threads": torch_threads,
        "sizes": rows,
    }

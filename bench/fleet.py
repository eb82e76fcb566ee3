"""``hitl bench fleet``: the fleet (``server.fleet``) against the raw physics it runs on.

For each fleet size N, measured in the same run:

- raw: N bare worker processes stepping their task with hold actions as fast as they can (the
  physics limit of this machine);
- fleet: the fleet free-running (no control-rate sleep). No robot asks for help
  (``assistance = false``: a waiting robot only holds, which would make the fleet cheaper the
  longer it runs), so every robot but one is driven by the policy and scored at every step.
  Robot 0 is under teleop (taken over again at each new episode) and receives operator commands
  at ``command_hz`` from another thread, as from a teleop device (commands that arrive between two
  ticks compose into one step).
  Reported: ticks/s, tick period p50/p99, total env steps/s, the control loop's CPU per env
  step, the teleoperated robot's action period (its control period: a tick moves only the
  robots whose physics has answered) and command-to-applied latency p50/p99 (from the command's
  arrival at the fleet to the tick that sends it to the worker);
- the fleet's share of the raw throughput.

The policy and uncertainty are the real ones (the bundled policy of each task, or ``policy``; ``signal``:
the asking signal, default the fleet's). For a policy that sees cameras the raw processes render its
task's cameras after every step too (``Task.images``), so the raw rate counts what the fleet's workers
must do, and the control loop's CPU is split further into the cameras' encoders (``encode``).
"""

from __future__ import annotations

import contextlib
import importlib.util
import multiprocessing as mp
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.procstats import descendant_pids, memory_mb, processes_cpu_seconds, worker_pids
from policy.checkpoint import read_info
from server.db import make_engine, migrate, session_factory
from server.errors import ServiceError
from server.fleet.fleet import Fleet
from server.settings import RobotGroup, Settings, bundled_policy
from server.workers import WORKERS
from sim.spaces import TeleopCommand

GOAL_SHARE_OF_RAW_AT_16 = 0.7  # fleet env steps/s against raw physics at 16 robots (docs/benchmarks/serving.md)
GOAL_SERVER_MB_PER_ROBOT = 5.0  # the server's resident memory growth per added robot


def _raw_worker(task_name: str, seconds: float, start, out, images: bool = False) -> None:
    from sim.registry import make_task

    task = make_task(task_name, images=images)
    task.reset(0)
    task.step(task.hold_action())  # compile / warm up before the clock starts
    if images:
        task.images()
    start.wait()
    n, t_end = 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        r = task.step(task.hold_action())
        if images:  # what a worker of a policy that sees renders at every step
            task.images()
        n += 1
        if r.done:
            task.reset(n)
    out.put(n)
    task.close()


def raw_throughput(task: str, n: int, seconds: float, images: bool = False) -> float:
    """Total env steps/s of ``n`` bare processes stepping in parallel (``images``: and rendering the
    task's cameras at each step)."""
    ctx = mp.get_context("spawn")
    start, out = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_raw_worker, args=(task, seconds, start, out, images), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    time.sleep(min(60.0, 3.0 + 1.5 * n))  # let every process build its simulator
    start.set()
    total = sum(out.get(timeout=seconds + 120) for _ in procs)
    for p in procs:
        p.join(timeout=30)
    return total / seconds


def _take_over(fleet: Fleet) -> None:
    """Robot 0 asks for help and the bench operator claims it (continuous mode: it keeps control)."""
    fleet.request_help(0, "benchmark")
    fleet.claim(0, "bench")


def available_workers() -> tuple[str, ...]:
    """The back ends whose physics runs apart from the control loop (all but ``in-process``), less
    those whose optional extra is not installed here (``ray``)."""
    names = [w for w in WORKERS if w != "in-process"]
    return tuple(w for w in names if w != "ray" or importlib.util.find_spec("ray") is not None)


def fleet_throughput(
    task: str,
    n: int,
    seconds: float,
    data_dir: Path,
    torch_threads: int = 1,
    command_hz: float = 30.0,
    worker: str = "process",
    robots_per_process: int = 8,
    device: str = "cpu",
    inference: str = "local",
    policy: Path | None = None,
    signal: str | None = None,
) -> dict:
    settings = Settings(
        data_dir=data_dir,
        control_hz=0,
        robots=[RobotGroup(task=task, count=n, policy=policy)],
        queue={"lease_seconds": 3600},
        inference={"torch_threads": torch_threads, "device": device, "backend": inference},
        workers={"kind": worker, "robots_per_process": robots_per_process},
        # every other robot stays under the policy: the full per-step cost, all the time; with assistance
        # off, the operator keeps robot 0 until its episode ends
        controller={"assistance": False, "hand_back": "continuous"} | ({"signal": signal} if signal else {}),
    )
    migrate(settings.db_url)
    rss_before = memory_mb()["rss_mb"]
    fleet = Fleet(settings, session_factory(make_engine(settings.db_url)))
    fleet.start()
    stop = threading.Event()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                _take_over(fleet)
                break
            except ServiceError:  # robot 0's simulator is still starting
                time.sleep(0.2)

        def operator() -> None:  # a teleop device streaming at command_hz; commands between ticks compose
            while not stop.wait(1.0 / command_hz):
                try:
                    fleet.command(0, "bench", TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), -1.0))
                except ServiceError:  # its episode ended: take the next one over too
                    with contextlib.suppress(ServiceError):
                        _take_over(fleet)

        threading.Thread(target=operator, daemon=True).start()
        time.sleep(1.0)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # the window opens once the operator's commands reach robot 0
            with fleet.lock:
                if fleet.robots[0].latencies:
                    break
            time.sleep(0.1)
        with fleet.lock:
            pids = worker_pids(fleet.robots.values())
        # the back end's own processes (a local Ray instance's raylet, GCS and idle workers), not the physics
        others = {k: p for k, p in descendant_pids().items() if p not in set(pids.values())}
        overhead = getattr(fleet.worker_factory, "overhead", None)  # the ray back end's API time in the loop
        overhead0 = (overhead.seconds, overhead.calls) if overhead is not None else None
        remote = _ray_inference(fleet)  # the inference actor's call time and its own compute time
        remote0 = _inference_times(remote)
        workers_cpu0, others_cpu0 = processes_cpu_seconds(pids), processes_cpu_seconds(others)
        with fleet.lock:
            steps0 = fleet.loop.env_steps
            ticks0 = fleet.ticks
            fleet.loop.tick_periods.clear()
            fleet.robots[0].latencies.clear()
            fleet.robots[0].action_periods.clear()
            cpu0 = fleet.loop.loop_cpu_seconds
            parts0 = _inference_cpu(fleet)
        time.sleep(seconds)
        with fleet.lock:
            steps = fleet.loop.env_steps - steps0
            ticks = fleet.ticks - ticks0
            periods = np.array(fleet.loop.tick_periods)
            lat = np.array(fleet.robots[0].latencies)
            teleop_periods = np.array(fleet.robots[0].action_periods)
            cpu = fleet.loop.loop_cpu_seconds - cpu0
            parts = {k: v - parts0.get(k, 0.0) for k, v in _inference_cpu(fleet).items()}
            controller = next(iter(fleet.robots.values())).slot.controller
            asking, signal_names = controller.asking, list(controller.signals)
        workers_cpu = processes_cpu_seconds(pids) - workers_cpu0
        others_cpu = processes_cpu_seconds(others) - others_cpu0
        if overhead is not None:
            ray_s, ray_calls = overhead.seconds - overhead0[0], overhead.calls - overhead0[1]
        calls_s, compute_s, n_calls = (b - a for a, b in zip(remote0, _inference_times(remote), strict=True))
        server = memory_mb()
        workers = [memory_mb(pid) for pid in pids.values()]
        peaks = [w["peak_rss_mb"] for w in workers if w["peak_rss_mb"] is not None]
        rss = [w["rss_mb"] for w in workers if w["rss_mb"] is not None]
    finally:
        stop.set()
        fleet.stop()
    teleop_p50 = float(np.quantile(teleop_periods, 0.5) * 1e3) if len(teleop_periods) else None
    return {
        "ticks_per_s": ticks / seconds,
        "tick_period_p50_ms": float(np.quantile(periods, 0.5) * 1e3) if len(periods) else None,
        "tick_period_p99_ms": float(np.quantile(periods, 0.99) * 1e3) if len(periods) else None,
        "env_steps_per_s": steps / seconds,
        "command_latency_p50_ms": float(np.quantile(lat, 0.5) * 1e3) if len(lat) else None,
        "command_latency_p99_ms": float(np.quantile(lat, 0.99) * 1e3) if len(lat) else None,
        "commands_applied": int(len(lat)),
        "actions_per_robot_per_s": steps / seconds / n,
        # CPU the control loop spent per env step: policy, signals and bookkeeping (one thread)
        "loop_cpu_ms_per_env_step": cpu / max(steps, 1) * 1e3,
        "loop_cpu_share": cpu / seconds,
        "env_steps_per_tick": steps / max(ticks, 1),
        # the same CPU split: the policy's chunks, each signal (score, decision, explanation), and the rest,
        # the loop's own (frames, recording, the control state, views); with inference on Ray the policy
        # and the signals run in the actor, and the loop's own is all of the loop's CPU
        "asking_signal": asking,
        "policy_cpu_ms_per_env_step": parts.get("policy", 0.0) / max(steps, 1) * 1e3,
        "encode_cpu_ms_per_env_step": parts.get("encode", 0.0) / max(steps, 1) * 1e3,  # a policy that sees
        "signals_cpu_ms_per_env_step": {n: parts.get(n, 0.0) / max(steps, 1) * 1e3 for n in signal_names},
        "loop_own_cpu_ms_per_env_step": (cpu - (sum(parts.values()) if inference == "local" else 0.0))
        / max(steps, 1)
        * 1e3,
        # CPU the physics processes spent per env step (stepping, building frames, pipes, switching)
        "workers_cpu_ms_per_env_step": workers_cpu / max(steps, 1) * 1e3,
        # CPU of the back end's other processes per env step (Ray's raylet, GCS and idle workers; ~0 else)
        "backend_processes_cpu_ms_per_env_step": others_cpu / max(steps, 1) * 1e3,
        # ray: the control loop's time in Ray's API (send, check, fetch), per tick and per call
        "ray_api_ms_per_tick": ray_s / max(ticks, 1) * 1e3 if overhead is not None else None,
        "ray_api_us_per_call": ray_s / max(ray_calls, 1) * 1e6 if overhead is not None else None,
        # inference = "ray": one actor call per tick; its time in the loop, and the part the actor spent computing
        "inference": inference,
        "inference_call_ms": calls_s / n_calls * 1e3 if remote is not None and n_calls else None,
        "inference_actor_compute_ms": compute_s / n_calls * 1e3 if remote is not None and n_calls else None,
        "inference_ray_overhead_ms_per_tick": (calls_s - compute_s) / n_calls * 1e3
        if remote is not None and n_calls
        else None,
        "teleop_action_period_p50_ms": teleop_p50,
        # target: command-to-applied p99 within one control period + 20 ms. A tick moves only the
        # robots whose physics answered, so the control period is the teleoperated robot's own:
        # the median time between two actions sent to it.
        "latency_target_ms": teleop_p50 + 20 if teleop_p50 is not None else None,
        "worker": worker,
        "worker_processes": len(workers),
        # resident memory: the server process before the fleet (and its policy) was built and at the end
        # of the window, and the physics processes (one robot each, or robots_per_process when pooled)
        "server_rss_before_fleet_mb": rss_before,
        "server_rss_mb": server["rss_mb"],
        "server_peak_rss_mb": server["peak_rss_mb"],
        # the server's peak shared by its robots (its growth per added robot is bench_fleet's slope)
        "server_peak_rss_mb_per_robot": server["peak_rss_mb"] / n if server["peak_rss_mb"] is not None else None,
        "worker_peak_rss_mb": max(peaks, default=None),
        "workers_rss_mb_per_robot": sum(rss) / n if rss else None,
        "workers_peak_rss_mb_per_robot": sum(peaks) / n if peaks else None,
    }


def _inference_cpu(fleet: Fleet) -> dict[str, float]:
    """CPU seconds so far per inference part ("policy", each signal), summed over the fleet's controllers."""
    out: dict[str, float] = {}
    controllers = {id(r.slot.controller): r.slot.controller for r in fleet.robots.values()}
    for controller in controllers.values():
        for part, seconds in controller.inference_cpu_s.items():
            out[part] = out.get(part, 0.0) + seconds
    return out


COMPARED = (
    "env_steps_per_s",
    "share_of_raw",
    "loop_cpu_ms_per_env_step",
    "loop_own_cpu_ms_per_env_step",
    "policy_cpu_ms_per_env_step",
    "env_steps_per_tick",
)


def compare_with(report: dict, before: dict) -> dict:
    """Each row of ``report`` beside the row of the same size and back end in ``before`` (the previous
    release's result of this benchmark): the figures both hold, (before, now), and what made ``before``."""

    def key(row: dict) -> tuple:
        return row["robots"], row.get("backend") or row.get("worker") or "process"  # earlier files name "worker"

    old = {key(r): r for r in before.get("sizes", [])}
    rows = []
    for row in report["sizes"]:
        prev = old.get(key(row))
        if prev is None:
            continue
        figures = {k: {"before": prev[k], "now": row[k]} for k in COMPARED if k in prev and k in row}
        signals = {
            n: {"before": prev["signals_cpu_ms_per_env_step"].get(n), "now": ms}
            for n, ms in row.get("signals_cpu_ms_per_env_step", {}).items()
            if n in prev.get("signals_cpu_ms_per_env_step", {})
        }
        rows.append({"robots": row["robots"], "backend": row["backend"], **figures, "signals": signals})
    return {"before": before.get("provenance"), "rows": rows}


def _ray_inference(fleet: Fleet):
    """The fleet's Ray inference back end (one policy version here), or None when it computes locally."""
    inference = next(iter(fleet.robots.values())).slot.controller.inference
    return inference if hasattr(inference, "handle") else None


def _inference_times(remote) -> tuple[float, float, int]:
    """(seconds in calls, seconds the actor computed, calls) so far; zeros without a Ray back end."""
    if remote is None:
        return 0.0, 0.0, 0
    compute, calls = remote.ray.get(remote.handle.busy.remote(), timeout=60)
    return remote.overhead_s, compute, calls


def _fleet_child(args: tuple, out) -> None:
    try:
        out.put(("ok", fleet_throughput(*args)))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        out.put(("error", f"{type(exc).__name__}: {exc}"))


def _fleet_in_fresh_process(*args) -> dict:
    """``fleet_throughput`` in a new process: each size's memory figures start from a clean server."""
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_fleet_child, args=(args, out))  # not a daemon: it starts the fleet's workers
    proc.start()
    try:
        status, value = out.get(timeout=900)
    finally:
        proc.join(timeout=60)
    if status != "ok":
        raise RuntimeError(f"fleet measurement failed: {value}")
    return value


def bench_fleet(
    task: str,
    sizes: list[int],
    seconds: float = 10.0,
    progress: bool = True,
    torch_threads: int = 1,
    command_hz: float = 30.0,
    workers: tuple[str, ...] | None = None,
    robots_per_process: int = 8,
    device: str = "cpu",
    inference: tuple[str, ...] = ("local",),
    policy: Path | None = None,
    signal: str | None = None,
) -> dict:
    """For each size: raw physics, then the fleet on each worker back end with each inference back end
    (each in a fresh process; default workers: every back end that runs physics in processes of its own
    and is installed here). A row's ``backend`` names both."""
    workers = tuple(workers) if workers is not None else available_workers()
    sees = bool(read_info(policy or bundled_policy(task))["policy"].get("cameras"))  # raw renders as its workers
    rows = []
    todo = [(n, w, i) for n in sizes for w in workers for i in inference]
    with tempfile.TemporaryDirectory() as tmp:
        raw = {}
        for n, worker, where in tqdm(todo, desc="bench fleet", disable=not progress):
            if n not in raw:
                raw[n] = raw_throughput(task, n, seconds, sees)
            args = (task, n, seconds, Path(tmp) / f"n{n}-{worker}-{where}", torch_threads, command_hz)
            fleet = _fleet_in_fresh_process(*args, worker, robots_per_process, device, where, policy, signal)
            p99, target = fleet["command_latency_p99_ms"], fleet["latency_target_ms"]
            rows.append(
                {
                    "robots": n,
                    "backend": worker if where == "local" else f"{worker}, inference on ray",
                    "raw_env_steps_per_s": raw[n],
                    **fleet,
                    "share_of_raw": fleet["env_steps_per_s"] / raw[n],
                    "latency_target_met": None if p99 is None or target is None else p99 <= target,
                }
            )
    growth = {}
    for backend in dict.fromkeys(r["backend"] for r in rows):  # the server's resident memory: its slope per robot
        pts = [(r["robots"], r["server_rss_mb"]) for r in rows if r["backend"] == backend and r["server_rss_mb"]]
        if len({n for n, _ in pts}) >= 2:
            growth[backend] = float(np.polyfit([n for n, _ in pts], [m for _, m in pts], 1)[0])
    return {
        "benchmark": "fleet",
        "task": task,
        "policy": str(policy) if policy is not None else None,
        "sees_cameras": sees,
        "device": device,
        "seconds_per_measurement": seconds,
        "server_torch_threads": torch_threads,
        "operator_command_hz": command_hz,
        "robots_per_process": robots_per_process,
        "sizes": rows,
        "server_mb_per_added_robot": growth,
        "goals": fleet_goals(rows, growth),
    }


def fleet_goals(rows: list[dict], growth: dict[str, float]) -> dict:
    """The goals and, per worker back end, whether this run met them (absent where it did not measure)."""
    return {
        "share_of_raw_at_16": GOAL_SHARE_OF_RAW_AT_16,
        "share_of_raw_at_16_met": {
            r["backend"]: r["share_of_raw"] >= GOAL_SHARE_OF_RAW_AT_16 for r in rows if r["robots"] == 16
        },
        "server_mb_per_added_robot": GOAL_SERVER_MB_PER_ROBOT,
        "server_mb_per_added_robot_met": {w: mb < GOAL_SERVER_MB_PER_ROBOT for w, mb in growth.items()},
    }

"""The harness every service benchmark shares: the real service in this process, a spawned client
process beside it, and the fleet's control rate and CPU measured over windows.

- ``LocalService``: ``create_app(settings)`` under uvicorn in a thread of this process, on a free
  127.0.0.1 port, its log in a file. The benchmarks and ``hitl docs screenshots`` run the real service
  this way, and can read the services its lifespan built (``app.state``).
- ``fresh_database``: the settings' data folder and a migrated database, for a benchmark's own tokens.
- ``wait_stepping``, ``Window``, ``measure``: wait until every robot is stepped, then measure a window
  (action periods, env steps/s, tick periods, where the machine's CPU went).
- ``ClientProcess``: the load generator in a spawned process (its own event loop and GIL), started,
  waited on until it says it is ready, and always reaped.
- ``seconds_bar``: the progress bar of a benchmark measured in seconds; ``timed``: the median wall
  time of a call (the serving-cost benchmarks).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import socket
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.procstats import TICKS_PER_SECOND, cpu_ticks, worker_pids


class LogCount(logging.FileHandler):
    """The server's log, to a file; counts warnings and errors and keeps the first few."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.warnings, self.first = 0, []

    def emit(self, record: logging.LogRecord) -> None:
        super().emit(record)
        if record.levelno >= logging.WARNING:
            self.warnings += 1
            if len(self.first) < 5:
                self.first.append(f"{record.levelname} {record.name}: {record.getMessage()}"[:300])


class LocalService:
    """``create_app(settings)`` under uvicorn, in a thread, on a socket bound to a free port."""

    def __init__(self, settings, log_path: Path) -> None:
        import uvicorn

        from server.app import RedactTokens
        from service.app import create_app

        # IPPROTO_TCP explicitly: asyncio sets TCP_NODELAY only on sockets whose ``proto`` says TCP (as
        # uvicorn's own, from getaddrinfo); with proto 0 every response would wait out Nagle + delayed ACK
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.app = create_app(settings)
        self.log = LogCount(log_path)
        self._redact = RedactTokens()
        self._loggers = [logging.getLogger(n) for n in ("uvicorn", "hitl")]
        self._saved = [(lg, lg.propagate, lg.level) for lg in self._loggers]
        for lg in self._loggers:
            lg.addHandler(self.log)
            lg.propagate = False
            lg.setLevel(logging.INFO)
        logging.getLogger("uvicorn.access").addFilter(self._redact)
        config = uvicorn.Config(self.app, log_config=None, log_level="info", access_log=True)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self):
        import httpx

        self.thread.start()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and self.thread.is_alive():
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(self.url + "/readyz").status_code == 200:
                    return self
            time.sleep(0.2)
        self.__exit__()
        tail = Path(self.log.baseFilename).read_text()[-2000:]
        raise RuntimeError(f"the service did not become ready; the end of its log:\n{tail}")

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)
        self.sock.close()
        logging.getLogger("uvicorn.access").removeFilter(self._redact)
        for lg, propagate, level in self._saved:
            lg.removeHandler(self.log)
            lg.propagate, lg.level = propagate, level
        self.log.close()


def fresh_database(settings):
    """The settings' data folder, created, and its database migrated; returns a session factory (the
    caller makes its tokens with it) and the engine to dispose of."""
    from server.db import make_engine, migrate, session_factory

    settings.data_dir.mkdir(parents=True)
    migrate(settings.db_url)
    engine = make_engine(settings.db_url)
    return session_factory(engine), engine


def seconds_bar(total: float, desc: str, progress: bool) -> tqdm:
    """A progress bar counting the seconds of a benchmark's measurement windows."""
    return tqdm(total=total, desc=desc, disable=not progress, bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s")


def reference_rate(before: dict, after: dict) -> float:
    """The fleet's env steps/s without the load: its rate drifts between windows (episode resets, the mix of
    phases), so the reference is the mean of the windows before and after."""
    return (before["env_steps_per_s"] + after["env_steps_per_s"]) / 2


def ms(values, q: float) -> float | None:
    return float(np.quantile(np.asarray(values), q) * 1e3) if len(values) else None


def dist(values) -> dict:
    return {"count": len(values), "p50_ms": ms(values, 0.5), "p99_ms": ms(values, 0.99), "max_ms": ms(values, 1)}


class Window:
    """The fleet's control rate over a measurement window (drained every second under the fleet lock), and
    where the machine's CPU went: this machine may be shared, and the report says how busy it was."""

    def __init__(self, fleet, client_pid: int | None = None, api_pids: list[int] = ()) -> None:
        """api_pids: the API processes of a service whose API runs apart from its runtime (this process)."""
        self.fleet = fleet
        self.pids = {"server_process": os.getpid()} | ({"client_process": client_pid} if client_pid else {})
        self.pids |= {f"api_process_{i}": pid for i, pid in enumerate(api_pids)}
        self.pids |= worker_pids(fleet.robots.values())
        renderer = getattr(getattr(fleet, "cameras", None), "process", None)  # the camera views' renderer, if running
        if renderer is not None and renderer.poll() is None:
            self.pids["camera_renderer"] = renderer.pid

    def start(self) -> None:
        f = self.fleet
        with f.lock:
            for r in f.robots.values():
                r.action_periods.clear()
            f.loop.tick_periods.clear()
            self.steps0, self.ticks0, self.loop_cpu0 = f.loop.env_steps, f.ticks, f.loop.loop_cpu_seconds
        self.periods, self.ticks, self.modes, self.samples = [], [], Counter(), 0
        self.t0, self.cpu0 = time.monotonic(), cpu_ticks(self.pids)

    def drain(self) -> None:
        f = self.fleet
        with f.lock:
            for r in f.robots.values():
                self.periods += r.action_periods
                r.action_periods.clear()
                self.modes[r.mode] += 1
            self.ticks += f.loop.tick_periods
            f.loop.tick_periods.clear()
        self.samples += 1

    def stop(self) -> dict:
        self.drain()
        f, seconds = self.fleet, time.monotonic() - self.t0
        periods = np.asarray(self.periods)
        return {
            "seconds": seconds,
            "action_period": dist(periods),
            "control_hz_p50": float(1 / np.quantile(periods, 0.5)) if len(periods) else None,
            "env_steps_per_s": (f.loop.env_steps - self.steps0) / seconds,
            "ticks_per_s": (f.ticks - self.ticks0) / seconds,
            "tick_period": dist(self.ticks),
            "robots_by_mode_mean": {m: n / self.samples for m, n in sorted(self.modes.items())},
            "control_loop_cpu_share": (f.loop.loop_cpu_seconds - self.loop_cpu0) / seconds,
            "cpu_cores": self._cores(seconds),
        }

    def _cores(self, seconds: float) -> dict:
        """Cores used on average: the machine, this benchmark's processes, and the rest (other users)."""
        t1 = cpu_ticks(self.pids)
        used = {k: (t1[k] - self.cpu0[k]) / TICKS_PER_SECOND / seconds for k in t1 if k in self.cpu0}
        out = {"machine_cores": os.cpu_count(), "machine_busy": used.pop("machine", None)}
        out["server_process"] = used.pop("server_process", None)
        out["client_process"] = used.pop("client_process", None)
        out["camera_renderer"] = used.pop("camera_renderer", None)
        api = [used.pop(k) for k in sorted(used) if k.startswith("api_process_")]
        if api:
            out["api_processes"] = sum(api)
        out["robot_workers"] = sum(used.values())
        if out["machine_busy"] is not None:
            ours = out["robot_workers"] + sum(api)
            ours += sum(out[k] or 0 for k in ("server_process", "client_process", "camera_renderer"))
            out["other_processes"] = max(0.0, out["machine_busy"] - ours)
        return out


def wait_stepping(fleet, timeout: float = 300.0) -> None:
    """Until every robot has been sent an action (its simulator is up)."""
    deadline = time.monotonic() + timeout
    while any(r.last_sent is None for r in fleet.robots.values()):
        if time.monotonic() > deadline:
            raise RuntimeError("not every robot started stepping in time")
        time.sleep(0.2)


class ClientProcess:
    """A benchmark's clients in a spawned process: ``target(params, go, out)`` puts ``("ready", ...)`` on
    ``out`` once set up, waits for ``go``, then puts its result (``("result", payload)``, anything else
    is a failure). ``with ClientProcess(...) as c:`` starts it and waits for ready; ``c.go()`` releases
    it; ``c.result(timeout)`` returns its payload or raises with its message; the process is always
    joined, and killed if it outlives the block."""

    def __init__(self, target, params: dict, name: str, ready_timeout: float = 300.0, join_timeout: float = 10.0):
        ctx = mp.get_context("spawn")
        self._go, self._out = ctx.Event(), ctx.Queue()
        self.process = ctx.Process(target=target, args=(params, self._go, self._out), name=name, daemon=True)
        self.name, self.ready_timeout, self.join_timeout = name, ready_timeout, join_timeout

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def __enter__(self) -> ClientProcess:
        self.process.start()
        try:
            kind, payload = self._out.get(timeout=self.ready_timeout)
            if kind != "ready":
                raise RuntimeError(f"{self.name} failed to start: {payload}")
        except BaseException:
            self.__exit__()
            raise
        return self

    def go(self) -> None:
        self._go.set()

    def result(self, timeout: float):
        kind, payload = self._out.get(timeout=timeout)
        if kind != "result":
            raise RuntimeError(f"{self.name} failed: {payload}")
        return payload

    def __exit__(self, *exc) -> None:
        self.process.join(timeout=self.join_timeout)
        if self.process.is_alive():
            self.process.kill()


def measure(window: Window, seconds: float, bar) -> dict:
    """Measures ``window`` for ``seconds``, draining it every second and advancing ``bar``."""
    window.start()
    last = time.monotonic()
    t_end = last + seconds
    while (left := t_end - time.monotonic()) > 0:
        time.sleep(min(1.0, left))
        window.drain()
        now = time.monotonic()
        bar.update(min(now - last, bar.total - bar.n))
        last = now
    return window.stop()


def timed(fn, repeats: int, device=None) -> float:
    """Median wall time in seconds over ``repeats`` calls after one warm-up call (a CUDA ``device`` is
    synchronised after each call, so the time is the work's, not its launch's)."""

    def run():
        fn()
        if device is not None and device.type == "cuda":
            import torch

            torch.cuda.synchronize(device)

    run()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return float(np.median(times))

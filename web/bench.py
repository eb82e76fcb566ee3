"""``hitl bench console``: what the operator console costs the fleet, with real browsers.

The service is the real one (``create_app`` under uvicorn in this process, ``server.local_service``),
with N lift-cube robots on the bundled policy, process workers, ``control_hz`` 10, the denoising metric
scored alongside (the console draws its field) and ``assistance = false`` (no robot asks, so every robot
is stepped at every tick and the mix of modes is the benchmark's).

1. warm-up, then ``idle_seconds`` with no browser: the fleet's env steps/s, control rate and CPU;
2. a spawned client process opens B pages of Debian's headless Chromium (each its own context and
   session, logged in through the form), each viewing a different robot, and waits until every page
   receives updates; then ``seconds`` with the browsers open, measured the same way. Each page counts
   the WebSocket messages and bytes it receives (what reaches the client).

The browsers run on this machine, reniced to ``nice`` (default 19): on a real deployment they run on
the operators' machines. Their CPU is reported apart ("other processes"), and the server's own extra
CPU (the console's tick, the proxy) is the server process's CPU with browsers minus without.
Goal: the fleet's env steps/s with the browsers at least 85% of without, and each browser receiving
updates at the control rate.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

from server.bench_api import _measure, _wait_stepping, _Window
from server.local_service import LocalService

GOAL_MAX_COST = 0.15
CHROMIUM = "/usr/bin/chromium"
READY_TIMEOUT_S = 600


def _client_process(p: dict, go, out) -> None:
    """B Chromium pages, each logged in and viewing robot i; counts what each page receives."""
    import os

    try:
        os.nice(p["nice"])
        from playwright.sync_api import sync_playwright

        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=p["chromium"], args=["--no-sandbox", "--use-gl=swiftshader"])
            pages, counts = [], []
            for i in range(p["browsers"]):
                page = browser.new_context(viewport={"width": 1280, "height": 800}).new_page()
                page.set_default_timeout(READY_TIMEOUT_S * 1000)
                count = {"messages": 0, "bytes": 0}

                def on_socket(ws, count=count) -> None:
                    def received(payload, count=count) -> None:
                        count["messages"] += 1
                        count["bytes"] += len(payload)

                    ws.on("framereceived", received)

                page.on("websocket", on_socket)
                page.goto(f"{p['url']}/console/login")
                page.fill("#token", p["token"])
                page.click("button[type=submit]")
                page.wait_for_url(f"{p['url']}/console/")
                page.get_by_role("combobox").click()
                page.get_by_role("option", name=f"{i} · ").first.click()
                pages.append(page)
                counts.append(count)
            pages[-1].wait_for_timeout(15_000)  # every page's scene is built and streaming
            out.put(("ready", None))
            go.wait()
            for c in counts:
                c["messages"] = c["bytes"] = 0
            t0 = time.monotonic()
            while time.monotonic() - t0 < p["seconds"]:
                pages[0].wait_for_timeout(500)  # lets playwright deliver the pages' events
            seconds = time.monotonic() - t0
            clients = [
                {"robot": i, "messages_per_s": c["messages"] / seconds, "bytes_per_s": c["bytes"] / seconds}
                for i, c in enumerate(counts)
            ]
            browser.close()
        out.put(("result", clients))
    except Exception as exc:  # reported to the parent, which fails the benchmark with it
        out.put(("error", repr(exc)))


def bench_console(
    robots: int = 16,
    browsers: int = 4,
    seconds: float = 30.0,
    idle_seconds: float = 20.0,
    task: str = "lift-cube",
    control_hz: float = 10.0,
    nice: int = 19,
    chromium: str = CHROMIUM,
    progress: bool = True,
) -> dict:
    from server.auth import create_token
    from server.db import make_engine, migrate, session_factory
    from server.settings import RobotGroup, Settings

    if browsers > robots:
        raise ValueError(f"--browsers ({browsers}) must not exceed --robots ({robots}): each views its own robot")
    if not Path(chromium).exists():
        raise FileNotFoundError(f"{chromium} not found: apt-get install -y chromium")
    with tempfile.TemporaryDirectory(prefix="hitl-bench-console-") as tmp:
        settings = Settings(
            data_dir=Path(tmp) / "var",
            control_hz=control_hz,
            robots=[RobotGroup(task=task, count=robots)],
            assistance=False,
            shadow_signals=["denoising"],
        )
        settings.data_dir.mkdir(parents=True)
        migrate(settings.db_url)
        engine = make_engine(settings.db_url)
        token = create_token(session_factory(engine), "bench-console", "viewer")
        engine.dispose()
        bar = tqdm(
            total=idle_seconds + seconds,
            desc="bench console",
            disable=not progress,
            bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s",
        )
        try:
            with LocalService(settings, Path(tmp) / "server.log") as svc:
                fleet, console = svc.app.state.fleet, svc.app.state.console
                _wait_stepping(fleet)
                time.sleep(3.0)  # warm-up
                idle = _measure(_Window(fleet), idle_seconds, bar)
                ctx = mp.get_context("spawn")
                go, out = ctx.Event(), ctx.Queue()
                p = {
                    "url": svc.url,
                    "token": token,
                    "browsers": browsers,
                    "seconds": seconds,
                    "nice": nice,
                    "chromium": chromium,
                }
                proc = ctx.Process(target=_client_process, args=(p, go, out), name="bench-browsers", daemon=True)
                proc.start()
                try:
                    kind, payload = out.get(timeout=READY_TIMEOUT_S)
                    if kind != "ready":
                        raise RuntimeError(f"the browsers did not start: {payload}")
                    stats0 = (console.stats.ticks, console.stats.tick_cpu_s, console.stats.frames_sent)
                    go.set()
                    loaded = _measure(_Window(fleet, proc.pid), seconds, bar)
                    stats1 = (console.stats.ticks, console.stats.tick_cpu_s, console.stats.frames_sent)
                    kind, clients = out.get(timeout=seconds + 120)
                    if kind != "result":
                        raise RuntimeError(f"the browsers failed: {clients}")
                finally:
                    proc.join(timeout=30)
                    if proc.is_alive():
                        proc.kill()
        finally:
            bar.close()
    window = loaded["seconds"]
    cost = 1.0 - loaded["env_steps_per_s"] / idle["env_steps_per_s"]
    rate = [c["messages_per_s"] for c in clients]
    console_stats = {
        "ticks_per_s": (stats1[0] - stats0[0]) / window,
        "tick_cpu_share_of_a_core": (stats1[1] - stats0[1]) / window,
        "atomic_frames_per_s_per_browser": (stats1[2] - stats0[2]) / window / browsers,
    }
    server_cpu = {k: w["cpu_cores"]["server_process"] for k, w in (("idle", idle), ("browsers", loaded))}
    return {
        "config": {
            "robots": robots,
            "browsers": browsers,
            "seconds": seconds,
            "idle_seconds": idle_seconds,
            "task": task,
            "control_hz": control_hz,
            "browser_nice": nice,
            "shadow_signals": ["denoising"],
        },
        "goal": {"max_cost_share": GOAL_MAX_COST, "updates_per_s_per_browser": control_hz},
        "idle": idle,
        "browsers": loaded,
        "clients": clients,
        "console": console_stats,
        "server_process_cores": server_cpu | {"added": server_cpu["browsers"] - server_cpu["idle"]},
        "fleet_cost_share": cost,
        "min_messages_per_s": min(rate),
        "met": cost <= GOAL_MAX_COST and console_stats["atomic_frames_per_s_per_browser"] >= 0.9 * control_hz,
        "command": "hitl bench console " + json.dumps({"robots": robots, "browsers": browsers, "seconds": seconds}),
    }

"""``hitl bench api``: the fleet service under concurrent API clients.

The server is the real one: ``create_app(settings)`` under uvicorn on 127.0.0.1 (a free port, access
log on, to a file), in this process, with N lift-cube robots on the bundled policy, process workers
and ``control_hz`` 10. Tokens are made with ``server.auth.create_token``. The clients run in a
separate (spawned) process, so that the load generator shares neither the server's event loop nor
its GIL; on one machine they still share its cores.

Phases:

1. start, wait for ``/readyz`` and for every robot to have received an action, 2 s of warm-up;
2. idle: ``idle_seconds`` with no client;
3. load: C clients for ``seconds``, each bounded (one request in flight at a time, paced):
   - REST pollers at ``poll_hz`` each, cycling robot list, robot detail, operator view, assistance
     queue and fleet metrics;
   - WebSocket command streams: one robot each, put under teleop (the robot asks through the fleet's
     ``request_help``, the client claims it through the API), commands at ``command_hz``, a REST
     heartbeat every second; the command round trip is timed to its ``accepted`` (or error) reply;
   - queue cyclers: wait for their robot's request in ``GET /assistance``, claim, command once (REST),
     heartbeat, release.
   The robots of streams and cyclers ask again as soon as they are autonomous (``request_help``, as
   ``bench.fleet`` does for its teleoperated robot): there is no API route that makes a robot ask.

The fleet runs as in ``hitl bench fleet``: ``assistance = false`` (no robot asks by itself, so the
fleet's mix of modes is the benchmark's, not the policy's) and ``hand_back = "continuous"`` (an
operator keeps a robot until release).

Control rate: the per-robot action period, the time between two actions the fleet sends to the same
robot (``Robot.action_periods``), pooled over all robots, and the env steps per second of the fleet
(``ControlLoop.env_steps``); both read from the fleet object in this process, idle and under load.

Errors: non-2xx answers other than the protocol's 429 ("send it again after the next tick") for a
command, WebSocket error replies, exceptions and timeouts (10 s). Refusals the protocol expects are
counted apart.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import tempfile
import threading
import time
from collections import Counter, deque
from pathlib import Path

from bench.harness import (
    ClientProcess,
    LocalService,
    LogCount,
    Window,
    dist,
    fresh_database,
    measure,
    ms,
    seconds_bar,
    wait_stepping,
)
from sim.spaces import TeleopCommand

API = "/api/v1"
POLL_KINDS = ("robots", "robot", "view", "queue", "metrics")
EXPECTED = {("command", 429), ("ws_command", 429)}  # the protocol's "send it again after the next tick"
TIMEOUT_S = 10.0
HEARTBEAT_S = 1.0
GOAL_CLIENTS, GOAL_ROBOTS, GOAL_CONTROL_RATIO, GOAL_REST_P99_MS = 50, 16, 1.2, 50.0


def plan_clients(clients: int, robots: int) -> dict:
    """How C clients split into WebSocket streams, queue cyclers (one robot each) and REST pollers."""
    ws = min(max(1, clients // 10), robots, clients)
    cyclers = min(max(1, clients // 25), robots - ws, clients - ws)
    return {"websocket_streams": ws, "queue_cyclers": cyclers, "rest_pollers": clients - ws - cyclers}


# -- the load generator (its own process) ---------------------------------------------------------------
class _Stats:
    def __init__(self) -> None:
        self.latency: dict[str, list[float]] = {}
        self.errors: Counter = Counter()
        self.refused: Counter = Counter()
        self.ws_states = 0
        self.t_end = float("inf")  # requests are made (and counted) until then

    def outcome(self, kind: str, status: int, seconds: float | None) -> bool:
        if seconds is not None:
            self.latency.setdefault(kind, []).append(seconds)
        if 200 <= status < 300:
            return True
        (self.refused if (kind, status) in EXPECTED else self.errors)[f"{kind}:{status}"] += 1
        return False

    def failed(self, kind: str, exc: BaseException) -> None:
        import httpx

        what = "timeout" if isinstance(exc, httpx.TimeoutException) else f"exception:{type(exc).__name__}"
        self.errors[f"{kind}:{what}"] += 1

    async def call(self, client, method: str, path: str, kind: str, **kw):
        if time.monotonic() >= self.t_end:
            return None
        t0 = time.perf_counter()
        try:
            r = await client.request(method, API + path, **kw)
        except Exception as exc:  # noqa: BLE001 - every failure is counted by kind
            self.failed(kind, exc)
            return None
        return r if self.outcome(kind, r.status_code, time.perf_counter() - t0) else None


def _command(sign: int) -> dict:
    return TeleopCommand.checked((0.002 * sign, 0.0, 0.0), (0.0, 0.0, 0.0), -1.0).to_dict()


async def _until(t: float) -> None:
    await asyncio.sleep(max(0.0, t - time.monotonic()))


async def _poller(i: int, client, stats: _Stats, p: dict, t_end: float) -> None:
    period = 1.0 / p["poll_hz"]
    t = time.monotonic() + period * i / max(1, p["rest_pollers"])  # spread the clients over one period
    k = i
    while True:
        await _until(t)
        if time.monotonic() >= t_end:
            return
        kind, rid = POLL_KINDS[k % len(POLL_KINDS)], (k * 7 + i) % p["robots"]
        path = {"robots": "/robots", "robot": f"/robots/{rid}", "view": f"/robots/{rid}/view"}.get(kind)
        path = path or {"queue": "/assistance", "metrics": "/metrics/fleet"}[kind]
        await stats.call(client, "GET", path, kind)
        k += 1
        t = max(t + period, time.monotonic())  # late: the next one goes at once, no burst to catch up


async def _wait_request(client, stats: _Stats, rid: int, t_end: float, count: bool = True) -> bool:
    """Until robot ``rid`` has an unclaimed request in the queue (False at ``t_end``)."""
    while time.monotonic() < t_end:
        if count:
            r = await stats.call(client, "GET", "/assistance", "queue")
        else:
            r = await client.get(API + "/assistance")
        if r is not None and any(q["robot_id"] == rid and q["holder"] is None for q in r.json()):
            return True
        await asyncio.sleep(0.2)
    return False


async def _cycler(rid: int, client, stats: _Stats, t_end: float) -> None:
    sign = 1
    while await _wait_request(client, stats, rid, t_end):
        if await stats.call(client, "POST", f"/robots/{rid}/claim", "claim") is None:
            await asyncio.sleep(0.2)
            continue
        await stats.call(client, "POST", f"/robots/{rid}/command", "command", json=_command(sign))
        sign = -sign
        await asyncio.sleep(0.5)
        await stats.call(client, "POST", f"/robots/{rid}/heartbeat", "heartbeat")
        await asyncio.sleep(0.5)
        await stats.call(client, "POST", f"/robots/{rid}/release", "release")


async def _stream(rid: int, client, ws, stats: _Stats, p: dict, t_end: float) -> None:
    """Commands at ``command_hz`` on the open socket ``ws``; replies come in order, so each ack or error
    reply answers the oldest command in flight. A REST heartbeat every second keeps the lease."""
    sent: deque = deque()
    owned = True

    async def receive() -> None:
        nonlocal owned
        try:
            async for msg in ws:
                if msg.startswith('{"state"'):
                    stats.ws_states += 1
                    continue
                reply = json.loads(msg)
                t0 = sent.popleft()
                status = 200 if reply.get("accepted") else int(reply["status"])
                ok = stats.outcome("ws_command", status, time.perf_counter() - t0)
                if not ok and reply.get("status") in (404, 409):  # lost the robot: claim it again
                    owned = False
            stats.errors["ws_receive:closed"] += 1
        except Exception as exc:  # noqa: BLE001 - counted, as every failure
            stats.failed("ws_receive", exc)

    async def heartbeat() -> None:
        nonlocal owned
        while time.monotonic() < t_end:
            if owned:
                await stats.call(client, "POST", f"/robots/{rid}/heartbeat", "heartbeat")
            elif await stats.call(client, "POST", f"/robots/{rid}/claim", "claim") is not None:
                owned = True
            await asyncio.sleep(HEARTBEAT_S)

    receiver, beater = asyncio.create_task(receive()), asyncio.create_task(heartbeat())
    period, sign, t = 1.0 / p["command_hz"], 1, time.monotonic()
    while time.monotonic() < t_end and not receiver.done():
        if owned:
            sent.append(time.perf_counter())
            try:
                await ws.send(json.dumps(_command(sign)))
            except Exception as exc:  # noqa: BLE001 - counted, as every failure
                stats.failed("ws_command", exc)
                sent.pop()
                break
            sign = -sign
        t = max(t + period, time.monotonic())
        await _until(min(t, t_end))
    deadline = time.monotonic() + TIMEOUT_S
    while sent and time.monotonic() < deadline and not receiver.done():  # the replies still in flight
        await asyncio.sleep(0.01)
    stats.errors.update({"ws_command:no_reply": len(sent)} if sent else {})
    beater.cancel()
    receiver.cancel()
    await asyncio.gather(receiver, beater, return_exceptions=True)


async def _load(p: dict, go, out) -> None:
    import httpx
    from websockets.asyncio.client import connect

    def client(token: str):
        headers = {"Authorization": f"Bearer {token}"}
        return httpx.AsyncClient(base_url=p["url"], headers=headers, timeout=TIMEOUT_S)

    stats = _Stats()
    ws_robots = list(range(p["websocket_streams"]))
    cycle_robots = list(range(len(ws_robots), len(ws_robots) + p["queue_cyclers"]))
    operators = [client(t) for t in p["operator_tokens"]]
    pollers = [client(p["viewer_token"]) for _ in range(p["rest_pollers"])]
    sockets = []
    async with contextlib.AsyncExitStack() as stack:
        for c in operators + pollers:
            await stack.enter_async_context(c)
        for rid, c in zip(ws_robots, operators, strict=False):  # set-up, not counted: own the robot, open the socket
            if not await _wait_request(c, stats, rid, time.monotonic() + 120, count=False):
                raise RuntimeError(f"robot {rid} never asked for help")
            (await c.post(f"{API}/robots/{rid}/claim")).raise_for_status()
            ws_url = p["url"].replace("http", "ws", 1) + f"{API}/robots/{rid}/teleop"
            auth = {"Authorization": c.headers["Authorization"]}  # not httpx's others (Connection: keep-alive)
            ws = await stack.enter_async_context(connect(ws_url, additional_headers=auth, max_size=2**24))
            await ws.recv()
            sockets.append(ws)
        for c in pollers:  # one connection each, open before the clock starts
            (await c.get("/healthz")).raise_for_status()
        out.put(("ready", None))
        await asyncio.to_thread(go.wait)
        cpu0, t_end = time.process_time(), time.monotonic() + p["seconds"]
        stats.t_end = t_end
        ops = iter(operators)
        tasks = [_stream(rid, next(ops), ws, stats, p, t_end) for rid, ws in zip(ws_robots, sockets, strict=True)]
        tasks += [_cycler(rid, next(ops), stats, t_end) for rid in cycle_robots]
        tasks += [_poller(i, c, stats, p, t_end) for i, c in enumerate(pollers)]
        await asyncio.gather(*tasks)
        cpu = time.process_time() - cpu0
    out.put(
        (
            "result",
            {
                "latency": stats.latency,
                "errors": dict(stats.errors),
                "refused": dict(stats.refused),
                "ws_states": stats.ws_states,
                "client_cpu_s": cpu,
            },
        )
    )


def _client_process(p: dict, go, out) -> None:
    try:
        asyncio.run(_load(p, go, out))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which fails loudly
        out.put(("failed", f"{type(exc).__name__}: {exc}"))


# -- the server (this process) ---------------------------------------------------------------------------
def _drill(fleet, robot_ids: list[int], stop: threading.Event) -> None:
    """The streams' and cyclers' robots ask for help whenever they are autonomous (no API route does)."""
    from server.errors import ServiceError

    while not stop.wait(0.05):
        for rid in robot_ids:
            robot = fleet.robots[rid]
            if robot.mode == "autonomous" and robot.frame is not None and fleet.queue.get(rid) is None:
                with contextlib.suppress(ServiceError):
                    fleet.request_help(rid, "bench api")


def _under_load(fleet, url: str, api_pids: list[int], plan: dict, tokens: dict, seconds: float, bar):
    """Starts the client process and measures the fleet while it runs."""
    stop = threading.Event()
    owned = list(range(plan["websocket_streams"] + plan["queue_cyclers"]))
    threading.Thread(target=_drill, args=(fleet, owned, stop), name="bench-drill", daemon=True).start()
    p = {**plan, **tokens, "url": url, "seconds": seconds, "robots": len(fleet.robots)}
    try:
        with ClientProcess(_client_process, p, "the client process") as clients:
            clients.go()
            load = measure(Window(fleet, clients.pid, api_pids), seconds, bar)
            return load, clients.result(timeout=seconds + 2 * TIMEOUT_S + 30)
    finally:
        stop.set()


@contextlib.contextmanager
def _service(settings, api_workers: int, tmp: Path):
    """(the fleet, the URL, the API processes' pids, the server log) of the service under test."""
    if not api_workers:
        with LocalService(settings, tmp / "server.log") as svc:
            yield svc.app.state.fleet, svc.url, [], svc.log
        return
    from service.replicas import ReplicatedService

    settings = settings.model_copy(update={"port": 0})
    log, runtime_log = LogCount(tmp / "runtime.log"), logging.getLogger("hitl")  # the API processes: api.log
    runtime_log.addHandler(log)
    try:
        with ReplicatedService(settings, api_workers, log_file=tmp / "api.log") as svc:
            svc.wait_ready()
            yield svc.fleet, svc.urls[0], svc.replicas.pids(), log
    finally:
        runtime_log.removeHandler(log)
        log.close()


def bench_api(
    robots: int = 16,
    clients: int = 50,
    seconds: float = 30.0,
    idle_seconds: float = 15.0,
    task: str = "lift-cube",
    policy: Path | None = None,
    worker: str = "process",
    control_hz: float = 10.0,
    poll_hz: float = 5.0,
    command_hz: float = 30.0,
    api_workers: int = 0,
    progress: bool = True,
) -> dict:
    """api_workers: 0, the API in the fleet runtime's process (``LocalService``); N, in N processes of its
    own (``service.replicas.ReplicatedService``), the runtime staying in this one."""
    from server.auth import create_token
    from server.settings import RobotGroup, Settings

    plan = plan_clients(clients, robots)
    plan.update(poll_hz=poll_hz, command_hz=command_hz)
    with tempfile.TemporaryDirectory(prefix="hitl-bench-api-") as tmp:
        settings = Settings(
            data_dir=Path(tmp) / "var",
            control_hz=control_hz,
            robots=[RobotGroup(task=task, count=robots, policy=policy)],
            workers={"kind": worker},
            controller={
                "assistance": False,
                "hand_back": "continuous",
            },  # no robot asks by itself; an operator keeps a robot until release
        )
        sessions, engine = fresh_database(settings)
        n_operators = plan["websocket_streams"] + plan["queue_cyclers"]
        tokens = {
            "viewer_token": create_token(sessions, "bench-viewer", "viewer"),
            "operator_tokens": [create_token(sessions, f"bench-operator-{i}", "operator") for i in range(n_operators)],
        }
        engine.dispose()
        bar = seconds_bar(idle_seconds + seconds, "bench api", progress)
        try:
            with _service(settings, api_workers, Path(tmp)) as (fleet, url, api_pids, svc_log):
                wait_stepping(fleet)
                time.sleep(2.0)  # warm-up
                idle = measure(Window(fleet, api_pids=api_pids), idle_seconds, bar)
                load, clients_result = _under_load(fleet, url, api_pids, plan, tokens, seconds, bar)
            log = {"warnings": svc_log.warnings, "first": svc_log.first}
        finally:
            bar.close()
    config = {"robots": robots, "clients": clients, "seconds": seconds, "idle_seconds": idle_seconds, "task": task}
    # the report's keys keep their names (docs/results/service/api.json): trigger_mode is the setting hand_back
    config.update(worker=worker, control_hz=control_hz, assistance=False, trigger_mode="continuous")
    config.update(api_workers=api_workers)
    return _report(config, plan, idle, load, clients_result, log)


def _report(config: dict, plan: dict, idle: dict, load: dict, res: dict, log: dict) -> dict:
    lat, seconds = res["latency"], config["seconds"]
    rest = [x for kind, v in lat.items() if kind != "ws_command" for x in v]
    ws = lat.get("ws_command", [])
    n_errors = sum(res["errors"].values())
    failed = sum(n for k, n in res["errors"].items() if ":timeout" in k or ":exception" in k)
    rest_p99 = ms(rest, 0.99)
    idle_p99, load_p99 = idle["action_period"]["p99_ms"], load["action_period"]["p99_ms"]
    ratio = load_p99 / idle_p99 if idle_p99 and load_p99 else None
    at_scale = config["clients"] >= GOAL_CLIENTS and config["robots"] >= GOAL_ROBOTS
    goals = [
        {
            "goal": f"{GOAL_CLIENTS} concurrent clients against a {GOAL_ROBOTS}-robot fleet with 0 errors",
            "value": {"errors": n_errors, "clients": config["clients"], "robots": config["robots"]},
            "met": n_errors == 0 and at_scale,
        },
        {
            "goal": "control rate: per-robot action period p99 under load within 20% of idle",
            "value": ratio,
            "target": f"<= {GOAL_CONTROL_RATIO}",
            "met": ratio is not None and ratio <= GOAL_CONTROL_RATIO,
        },
        {
            "goal": f"REST latency p99 under {GOAL_REST_P99_MS:g} ms",
            "value": rest_p99,
            "target": f"< {GOAL_REST_P99_MS:g}",
            "met": rest_p99 is not None and rest_p99 < GOAL_REST_P99_MS,
        },
    ]
    return {
        "benchmark": "api",
        "config": config,
        "clients": {k: plan[k] for k in ("rest_pollers", "websocket_streams", "queue_cyclers")},
        "client_rates": {"poll_hz": plan["poll_hz"], "command_hz": plan["command_hz"], "heartbeat_s": HEARTBEAT_S},
        "requests": {
            "total": len(rest) + len(ws) + failed,
            "per_s": (len(rest) + len(ws) + failed) / seconds,
            "rest": len(rest),
            "rest_per_s": len(rest) / seconds,
            "ws_commands": len(ws),
            "ws_commands_per_s": len(ws) / seconds,
            "ws_state_messages": res["ws_states"],
            # paced clients send less when answers come late: what the schedule asked for, and what was sent
            "polls_offered_per_s": plan["rest_pollers"] * plan["poll_hz"],
            "polls_per_s": sum(len(lat.get(k, [])) for k in POLL_KINDS) / seconds,
            "ws_commands_offered_per_s": plan["websocket_streams"] * plan["command_hz"],
        },
        "rest_latency": {**dist(rest), "by_kind": {k: dist(v) for k, v in sorted(lat.items()) if k != "ws_command"}},
        "ws_command_ack_latency": dist(ws),
        "errors": {"total": n_errors, "by_kind": res["errors"]},
        "refused_as_expected": res["refused"],
        "control": {
            "definition": "action period: seconds between two actions the fleet sends to the same robot, pooled "
            "over all robots (Robot.action_periods); env steps/s: ControlLoop.env_steps",
            "idle": idle,
            "load": load,
        },
        "client_process_cpu_share": res["client_cpu_s"] / seconds,
        "server_log": log,
        "goals": goals,
        "goals_met": all(g["met"] for g in goals),
    }

"""The API apart from the control loop: a fleet runtime in this process, API processes of their own
(real uvicorn servers on 127.0.0.1), the database deciding concurrent claims, on SQLite and PostgreSQL."""

import os
import signal
import subprocess
import sys
import threading
import uuid
from multiprocessing.connection import Client
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text

from server import lease
from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.runtime.client import RemoteFleet, RuntimeUnavailable, robot_lease
from server.runtime.wire import Call, Hello
from server.settings import RobotGroup, Settings
from service.replicas import ReplicatedService
from tests.helpers import free_port, tiny_policy_folder, wait_for

API = "/api/v1"
OPERATORS = 8


def _service(root, database_url: str | None):
    # a lineage is named after its folder: a unique name keeps tests apart on one PostgreSQL database
    policy = tiny_policy_folder(root / f"runtime-{uuid.uuid4().hex[:8]}", "lift-cube", threshold=-1.0)  # asks at once
    settings = Settings(
        data_dir=root / "var",
        database_url=database_url,
        port=0,
        robots=[RobotGroup(task="lift-cube", count=2, policy=policy)],
        workers={"kind": "in-process"},
        controller={"budget": 3, "cooldown": 0},  # robots ask again at once after a hand-back
        queue={"lease_seconds": 5.0},
        control_hz=20,
        console=False,
    )
    settings.data_dir.mkdir(parents=True)
    migrate(settings.db_url)
    engine = make_engine(settings.db_url)
    if database_url is not None:  # one database for the session: no claim lease left from another test
        with engine.begin() as conn:
            conn.execute(text("DELETE FROM job_leases"))
    sessions = session_factory(engine)
    tag = uuid.uuid4().hex[:6]
    tokens = {role: create_token(sessions, f"{role}-{tag}", role) for role in ("viewer", "admin")}
    tokens |= {f"op{i}": create_token(sessions, f"op{i}-{tag}", "operator") for i in range(OPERATORS)}
    return settings, sessions, tokens, engine


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def replicated(request, tmp_path_factory):
    url = None if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    settings, sessions, tokens, engine = _service(tmp_path_factory.mktemp(f"runtime-{request.param}"), url)
    with ReplicatedService(settings, workers=2, separate_ports=True, log_file=settings.data_dir / "api.log") as svc:
        svc.wait_ready(timeout=180)
        svc.tokens, svc.sessions = tokens, sessions
        yield svc
    engine.dispose()


def _h(svc, who: str) -> dict:
    return {"Authorization": f"Bearer {svc.tokens[who]}"}


def _get(url: str, svc, path: str):
    return httpx.get(f"{url}{API}{path}", headers=_h(svc, "viewer")).json()


def _mode(url: str, svc, rid: int) -> str:
    return _get(url, svc, f"/robots/{rid}")["mode"]


def _waiting(svc, rid: int) -> None:
    """Until the runtime shows robot ``rid`` asking and every API process's queue lists it."""
    wait_for(lambda: svc.fleet.view(rid).mode == "waiting" and svc.fleet.queue.get(rid) is not None)
    for url in svc.urls:
        wait_for(
            lambda u=url: (
                rid in [r["robot_id"] for r in httpx.get(f"{u}{API}/assistance", headers=_h(svc, "viewer")).json()]
            )
        )


def _release_all(svc) -> None:
    for rid in (0, 1):
        req = svc.fleet.queue.get(rid)
        if req is not None and req.holder is not None:
            who = next(k for k in svc.tokens if k.startswith("op") and req.holder.startswith(k + "-"))
            httpx.post(f"{svc.urls[0]}{API}/robots/{rid}/release", headers=_h(svc, who)).raise_for_status()


def test_two_api_processes_serve_one_fleet(replicated):
    svc = replicated
    a, b = svc.urls
    assert len(set(svc.replicas.pids())) == 2 and os.getpid() not in svc.replicas.pids()
    _release_all(svc)
    _waiting(svc, 0)
    robots = [httpx.get(f"{u}{API}/robots", headers=_h(svc, "viewer")).json() for u in (a, b)]
    assert [r["id"] for r in robots[0]] == [r["id"] for r in robots[1]] == [0, 1]
    assert httpx.get(f"{a}{API}/robots/7", headers=_h(svc, "viewer")).status_code == 404

    claim = httpx.post(f"{a}{API}/robots/0/claim", headers=_h(svc, "op0"))
    assert claim.status_code == 200, claim.text
    assert claim.json()["holder"] is not None  # the lease is the claimant's at once
    for url in (a, b):  # the runtime's next tick applies the claim; each API process shows it within a snapshot
        wait_for(lambda u=url: _mode(u, svc, 0) == "teleop", timeout=2.0)
    other = httpx.post(f"{b}{API}/robots/0/claim", headers=_h(svc, "op1"))
    assert other.status_code == 409 and "another operator" in other.json()["detail"]

    command = {"delta_pos": [0.01, 0.0, 0.0], "delta_rot": [0.0, 0.0, 0.0], "gripper": 1.0}
    assert httpx.post(f"{b}{API}/robots/0/command", headers=_h(svc, "op0"), json=command).status_code == 200
    assert httpx.post(f"{b}{API}/robots/0/command", headers=_h(svc, "op1"), json=command).status_code == 409
    wait_for(lambda: svc.fleet.view(0).assisted_steps >= 1)  # the runtime applied it at a tick

    released = httpx.post(f"{b}{API}/robots/0/release", headers=_h(svc, "op0"))
    assert released.status_code == 200
    wait_for(lambda: _mode(b, svc, 0) != "teleop", timeout=2.0)  # handed back at the runtime's next tick
    assert lease.holder(svc.sessions, robot_lease(0)) == (None, None)  # the next claim need not wait
    _waiting(svc, 0)
    assert httpx.post(f"{b}{API}/robots/0/claim", headers=_h(svc, "op1")).status_code == 200
    httpx.post(f"{b}{API}/robots/0/release", headers=_h(svc, "op1")).raise_for_status()

    paused = httpx.post(f"{a}{API}/robots/1/pause", headers=_h(svc, "admin"))
    assert paused.status_code == 200 and paused.json()["mode"] == "paused"
    wait_for(lambda: _mode(b, svc, 1) == "paused", timeout=2.0)
    assert httpx.post(f"{b}{API}/robots/1/resume", headers=_h(svc, "admin")).status_code == 200
    assert httpx.post(f"{b}{API}/robots/1/pause", headers=_h(svc, "viewer")).status_code == 403

    schedule = httpx.get(f"{a}{API}/finetune-schedule", headers=_h(svc, "viewer")).json()
    assert schedule["schedule"] == svc.settings.finetune.schedule  # the runtime's scheduler, as it reports it
    metrics = httpx.get(f"{b}{API}/metrics/fleet", headers=_h(svc, "viewer")).json()
    assert metrics["ticks"] > 0 and sum(metrics["robots_by_mode"].values()) == 2


def test_concurrent_claims_through_both_api_processes_give_one_lease(replicated):
    svc = replicated
    _release_all(svc)
    for round_ in range(3):
        _waiting(svc, 0)
        go, answers = threading.Barrier(OPERATORS), {}

        def claim(i: int, go=go, answers=answers) -> None:
            url = svc.urls[i % 2]  # half the operators at each API process
            with httpx.Client(headers=_h(svc, f"op{i}"), timeout=30) as client:
                client.get(f"{url}/healthz")  # connected before the race
                go.wait()
                answers[i] = client.post(f"{url}{API}/robots/0/claim")

        threads = [threading.Thread(target=claim, args=(i,)) for i in range(OPERATORS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        won = [i for i, r in answers.items() if r.status_code == 200]
        assert len(won) == 1, {i: (r.status_code, r.text[:80]) for i, r in answers.items()}
        assert all(r.status_code == 409 for i, r in answers.items() if i not in won), round_
        winner = won[0]
        held_by, _ = lease.holder(svc.sessions, robot_lease(0))
        assert held_by.startswith(f"op{winner}-")  # the database's one lease
        assert svc.fleet.queue.get(0).holder == held_by  # and the runtime's
        httpx.post(f"{svc.urls[0]}{API}/robots/0/release", headers=_h(svc, f"op{winner}")).raise_for_status()


def test_an_api_process_that_dies_is_started_again(replicated):
    svc = replicated
    before = svc.replicas.pids()
    os.kill(before[0], signal.SIGKILL)
    wait_for(lambda: svc.replicas.restarts >= 1 and len(svc.replicas.pids()) == 2, timeout=30)
    svc.wait_ready(timeout=120)  # the new one took the same socket
    assert set(svc.replicas.pids()) != set(before)
    assert httpx.get(f"{svc.urls[0]}{API}/robots", headers=_h(svc, "viewer")).status_code == 200
    assert svc.fleet.ticks > 0  # the fleet never stopped


def test_the_runtime_refuses_a_wrong_key_and_answers_only_port_calls(replicated):
    svc = replicated
    with pytest.raises(Exception):  # noqa: B017 - multiprocessing's AuthenticationError, or a reset
        Client(svc.host.address, family="AF_INET", authkey=b"not the key")
    remote = RemoteFleet(svc.settings, svc.host.address, svc.host.authkey, svc.sessions, who="test")
    with Client(svc.host.address, family="AF_INET", authkey=svc.host.authkey) as conn:
        conn.send(Hello("calls", "test"))
        conn.send(Call("stop", ()))  # a Fleet method, not a port call
        assert conn.recv().error[0] == 400
    wrong = RemoteFleet(svc.settings, svc.host.address, b"not the key", svc.sessions, who="test")
    with pytest.raises(RuntimeUnavailable):
        wrong.pause(0)
    assert remote.start(timeout=30).views()[0].slot.version == svc.fleet.view(0).slot.version
    remote.stop()


def test_a_console_log_in_through_one_api_process_holds_at_the_other(replicated):
    svc = replicated
    a, b = svc.urls
    login = httpx.post(f"{a}/console/login", data={"token": svc.tokens["op0"]}, follow_redirects=False)
    assert login.status_code == 303
    cookies = dict(login.cookies)
    assert httpx.get(f"{b}/console/", cookies=cookies).status_code == 200  # the session is in the database
    assert httpx.post(f"{b}/console/logout", cookies=cookies, follow_redirects=False).status_code == 303
    assert httpx.get(f"{a}/console/", cookies=cookies).status_code == 401  # logged out everywhere at once


def test_a_robots_timeline_crosses_as_tails_and_is_rebuilt_as_the_runtime_has_it():
    from types import SimpleNamespace

    from server.fleet.robot import U_HISTORY, Robot, TimelinePoint
    from server.runtime.host import RuntimeHost
    from server.runtime.wire import portable, timeline_since

    slot = SimpleNamespace(version=1, path="policy", task="lift-cube", lineage="lift")
    robot = Robot(0, "lift-cube", slot, seed=0, inbox=None, episode_id=1)
    remote = RemoteFleet(Settings(), ("127.0.0.1", 1), b"key", sessions=None)  # nothing connects here
    marks, sizes = {}, []
    for step in range(2 * U_HISTORY + 7):
        if step == U_HISTORY + 3:  # a new episode starts a new timeline
            robot.episode_id, robot.timeline = 2, type(robot.timeline)(maxlen=U_HISTORY)
        t = step // 2  # two records per clock: the second updates the first (a robot holding while it waits)
        robot.record(TimelinePoint(t, "waiting" if step % 2 else "autonomous", float(step), None))
        if step % 3:
            continue
        robot.publish()
        crossed = portable(robot.view, RuntimeHost._since(marks, robot.view))
        marks[0] = timeline_since(robot.view)
        sizes.append(len(crossed.timeline.points))
        assert remote._local(crossed, slot).timeline == robot.view.timeline, step
    assert max(sizes[2:]) <= 3 < U_HISTORY  # tails, not whole timelines, once it has started


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_hitl_serve_with_api_workers_serves_and_leaves_no_api_process_when_killed(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1e9)
    config = tmp_path / "fleet.toml"
    config.write_text(
        f'data_dir = "{tmp_path / "var"}"\ncontrol_hz = 20\nconsole = false\n[workers]\nkind = "in-process"\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    cmd = [
        sys.executable,
        "-m",
        "hitl.cli",
        "serve",
        "--config",
        str(config),
        "--port",
        str(port),
        "--api-workers",
        "1",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: _ready(url), timeout=180)
        api = [p for p in _children(proc.pid) if _serves(p)]
        assert len(api) == 1  # the API answers from a process of its own
        proc.send_signal(signal.SIGKILL)  # the runtime's process, as a crash takes it
        proc.wait(timeout=30)
        wait_for(lambda: not _alive(api[0]), timeout=30)  # the API process follows it
        with pytest.raises(httpx.ConnectError):
            httpx.get(url + "/healthz", timeout=2)  # and frees the port
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _ready(url: str) -> bool:
    try:
        return httpx.get(url + "/readyz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _serves(pid: int) -> bool:
    """Whether the process holds a listening TCP socket (an API process does; the runtime's own listener is
    on another port, in the parent)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").glob("*"):
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    listening = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if cols[3] == "0A":  # LISTEN
                listening.add(cols[9])
    return bool(inodes & listening)

"""Faults: a worker that dies, a server killed mid-takeover, and a clean SIGTERM."""

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from mcap.reader import make_reader

from server.auth import create_token
from server.db import EpisodeRecord, SegmentRecord, make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from storage.paths import in_store
from storage.segments import read_segment
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for


def _worker_pid(name):
    """The live worker process of that name among this process's children (the service runs here)."""
    alive = [p for p in multiprocessing.active_children() if p.name == name and p.is_alive()]
    return alive[-1].pid if alive else None


def _sessions(settings):
    migrate(settings.db_url)
    return session_factory(make_engine(settings.db_url))


def _asking_fleet(tmp_path, count: int = 1, **extra):
    """Settings of robots that ask at once (threshold -1), their database, and an operator's headers."""
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=count, policy=policy)],
        control_hz=20,
        controller={"budget": 100},
        **extra,
    )
    sessions = _sessions(settings)
    return settings, sessions, {"Authorization": f"Bearer {create_token(sessions, 'op', 'operator')}"}


def _claim_robot_0(api, h) -> None:
    wait_for(lambda: httpx.get(api + "/robots/0", headers=h).json()["mode"] == "waiting")
    assert httpx.post(api + "/robots/0/claim", headers=h).status_code == 200


def _assert_segments_closed_by_worker_fault(settings, sessions) -> None:
    """Every takeover segment is closed with ``worker-fault``, in its row and in its file's end message."""
    with sessions() as s:
        rows = s.query(SegmentRecord).all()
        assert rows and all(r.status == "closed" and r.ended_by == "worker-fault" for r in rows)
    ends = [read_segment(in_store(settings.data_dir, r.path)).end for r in rows]
    assert all(e["status"] == "closed" and e["ended_by"] == "worker-fault" for e in ends)  # the file says why


def test_a_dead_worker_faults_restarts_and_closes_its_segment(tmp_path):
    settings, sessions, h = _asking_fleet(tmp_path)
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        _claim_robot_0(api, h)
        pid = _worker_pid("robot-0")  # the service's worker process, as the OS shows it
        os.kill(pid, signal.SIGKILL)
        robot = wait_for(lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] == "faulted" and r)
        assert "exited" in robot["fault"] or "broke" in robot["fault"]
        _assert_segments_closed_by_worker_fault(settings, sessions)
        # restarted with backoff, then the policy runs (and, with this threshold, asks) again
        again = wait_for(
            lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] in ("autonomous", "waiting") and r, 30
        )
        restarted = wait_for(lambda: _worker_pid("robot-0"))
        assert again["restarts"] == 1 and restarted != pid
        # the restarted physics runs below the control loop again
        assert wait_for(lambda: os.getpriority(os.PRIO_PROCESS, restarted) == settings.workers.niceness)
        outcomes = [e["outcome"] for e in httpx.get(api + "/episodes", headers=h).json()]
        assert "faulted" in outcomes  # the interrupted episode is closed, not left open


def test_a_dead_pool_process_faults_its_robots_which_restart_on_a_new_one(tmp_path):
    settings, sessions, h = _asking_fleet(tmp_path, 2, workers={"kind": "pool", "robots_per_process": 2})
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        _claim_robot_0(api, h)
        host = _worker_pid("robots-0")  # both robots' physics, in one process
        assert host is not None and _worker_pid("robots-1") is None
        os.kill(host, signal.SIGKILL)
        for rid in (0, 1):  # each faults (then restarts after a 1 s backoff)
            robot = wait_for(lambda rid=rid: (r := httpx.get(api + f"/robots/{rid}", headers=h).json())["fault"] and r)
            assert "exited" in robot["fault"] or "broke" in robot["fault"]
        with sessions() as s:
            rows = s.query(SegmentRecord).all()
            assert rows and all(r.status == "closed" and r.ended_by == "worker-fault" for r in rows)
        for rid in (0, 1):  # both run again, on a new process
            wait_for(
                lambda rid=rid: (
                    httpx.get(api + f"/robots/{rid}", headers=h).json()["mode"] in ("autonomous", "waiting")
                ),
                30,
            )
        restarted = [p for p in multiprocessing.active_children() if p.is_alive() and p.name.startswith("robots-")]
        assert restarted and all(p.pid != host for p in restarted)


def test_a_dead_ray_actor_faults_its_robot_mid_takeover_which_restarts_on_the_restarted_actor(tmp_path, ray_local):
    settings, sessions, h = _asking_fleet(tmp_path, workers={"kind": "ray"}, ray={"cpus_per_actor": 0.5})
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        _claim_robot_0(api, h)
        worker = svc.app_state().fleet.robots[0].worker
        pid = ray_local.get(worker.host.handle.pid.remote(), timeout=60)
        assert pid != os.getpid()  # the robot's physics runs in its actor's process
        os.kill(pid, signal.SIGKILL)
        robot = wait_for(lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] == "faulted" and r)
        assert "died" in robot["fault"] or "not open" in robot["fault"]
        _assert_segments_closed_by_worker_fault(settings, sessions)
        again = wait_for(
            lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] in ("autonomous", "waiting") and r, 60
        )
        assert again["restarts"] >= 1
        restarted = svc.app_state().fleet.robots[0].worker
        assert ray_local.get(restarted.host.handle.pid.remote(), timeout=60) != pid  # Ray restarted the actor
        outcomes = [e["outcome"] for e in httpx.get(api + "/episodes", headers=h).json()]
        assert "faulted" in outcomes  # the interrupted episode is closed, not left open


def _serve(config, port):
    return subprocess.Popen(
        [sys.executable, "-m", "hitl.cli", "serve", "--config", str(config), "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _ready(url, timeout=120):
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if httpx.get(url + "/readyz").status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise AssertionError("service did not start")


def _standard_read(path):
    """Every message of an MCAP file through the ``mcap`` library's indexed (seeking) reader, as any
    MCAP tool reads it: it needs the file's summary, footer and closing magic."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary() is not None and reader.get_summary().chunk_indexes
        return [(c.topic, json.loads(m.data)) for _, c, m in reader.iter_messages()]


def _asking_config(tmp_path, extra: str = ""):
    """A config file of one lift-cube robot that asks at once (threshold -1), the settings it loads,
    their database and an operator's headers; ``extra``: more TOML lines."""
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)
    config = tmp_path / "fleet.toml"
    config.write_text(
        f'data_dir = "{tmp_path / "var"}"\ncontrol_hz = 20\n{extra}[controller]\nbudget = 100\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    settings = Settings.load(config)
    sessions = _sessions(settings)
    return config, settings, sessions, {"Authorization": f"Bearer {create_token(sessions, 'op', 'operator')}"}


def _drive(api: str, h: dict, n: int, dz: float) -> list:
    """Claims robot 0 once it waits, then sends ``n`` distinct commands, each applied before the next;
    returns their ``delta_pos`` in order."""
    wait_for(lambda: httpx.get(api + "/robots/0", headers=h).json()["mode"] == "waiting")
    assert httpx.post(api + "/robots/0/claim", headers=h).status_code == 200
    sent = []
    for i in range(n):
        before = httpx.get(api + "/robots/0", headers=h).json()["assisted_steps"]
        cmd = {"delta_pos": [0.0, 0.0, dz * (i + 1)], "gripper": -1}
        assert httpx.post(api + "/robots/0/command", json=cmd, headers=h).status_code == 200
        sent.append(cmd["delta_pos"])
        wait_for(lambda b=before: httpx.get(api + "/robots/0", headers=h).json()["assisted_steps"] > b)
    return sent


def _restart_to_recover(config, port: int, url: str) -> None:
    """Starts the server on ``config`` and stops it once ready: its start recovers what a crash left open."""
    proc = _serve(config, port)
    try:
        _ready(url)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)


@pytest.mark.parametrize(
    ("sig", "status", "ended_by"),
    [(signal.SIGKILL, "recovered", "crash-recovered"), (signal.SIGTERM, "closed", "service-stopped")],
)
def test_a_takeover_survives_the_server_stopping(tmp_path, sig, status, ended_by):
    config, settings, sessions, h = _asking_config(tmp_path, "[recording]\nepisodes = true\n")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    api = url + "/api/v1"
    proc = _serve(config, port)
    try:
        _ready(url)
        sent = _drive(api, h, 5, 0.001)
        time.sleep(1.5)  # past the 1 s flush interval: every accepted command is on disk
        proc.send_signal(sig)
        # the process ends by the signal (uvicorn re-raises SIGTERM once its graceful shutdown is done)
        assert proc.wait(timeout=60) == -sig
    finally:
        if proc.poll() is None:
            proc.kill()
    if sig == signal.SIGKILL:
        with sessions() as s:
            row = s.query(SegmentRecord).one()
            assert row.status == "open"  # the crash left it open, its file cut off:
            with pytest.raises(Exception, match="magic|footer|summary|EndOfFile|Invalid|record"):
                _standard_read(in_store(settings.data_dir, row.path))
        _restart_to_recover(config, port, url)
    with sessions() as s:
        row = s.query(SegmentRecord).one()
        assert row.status == status and row.ended_by == ended_by and row.steps >= len(sent)
        assert not Path(row.path).is_absolute()  # relative to data_dir: the folder can move
        path = in_store(settings.data_dir, row.path)
        interrupted = s.query(EpisodeRecord).filter(EpisodeRecord.outcome.is_(None)).all()
        assert not interrupted  # no episode row is left open
        first = s.query(EpisodeRecord).order_by(EpisodeRecord.id).first()
    messages = _standard_read(path)
    commands = [m["command"]["delta_pos"] for topic, m in messages if topic == "/takeover/step"]
    assert commands[: len(sent)] == sent  # every command accepted before the last flush, in order
    end = [m for topic, m in messages if topic == "/takeover/end"]
    assert len(end) == 1 and end[0]["status"] == status and end[0]["ended_by"] == ended_by
    expected = "interrupted" if sig == signal.SIGKILL else "stopped"
    assert first.outcome == expected and first.ended_at is not None
    if sig == signal.SIGKILL:  # the episode file open at the crash is a complete MCAP too
        episode = _standard_read(in_store(settings.data_dir, first.path))
        outcome = [m for topic, m in episode if topic == "/outcome"]
        assert outcome == [{"success": False, "steps": first.steps, "reason": "interrupted"}]


def test_whole_episodes_are_recorded_when_asked(tmp_path):
    from storage.episodes import read_episode

    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1e9)  # never asks: autonomous
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        control_hz=0,
        recording={"episodes": True},
    )
    sessions = _sessions(settings)
    h = {"Authorization": f"Bearer {create_token(sessions, 'viewer', 'viewer')}"}
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        done = wait_for(lambda: [e for e in httpx.get(api + "/episodes", headers=h).json() if e["outcome"]], 120)
    from server.db import EpisodeRecord

    with sessions() as s:
        row = s.get(EpisodeRecord, done[-1]["id"])
    ep = read_episode(in_store(settings.data_dir, row.path))
    assert len(ep) == row.steps == done[-1]["steps"] and ep.outcome is not None
    assert set(ep.sources) == {"policy"}


def test_a_dead_inference_actor_holds_the_fleet_which_resumes_when_ray_restarts_it(tmp_path, ray_local):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1e9)  # never asks: the policy drives
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=2, policy=policy)],
        workers={"kind": "in-process"},
        inference={"backend": "ray", "cpus": 0.5},
        recording={"episodes": True},
        control_hz=20,
        console=False,
    )
    sessions = _sessions(settings)
    with Service(settings) as svc:
        fleet = svc.app_state().fleet
        inference = fleet.robots[0].slot.controller.inference
        pid = ray_local.get(inference.handle.pid.remote(), timeout=60)
        assert pid != os.getpid()  # the policy and its signals run in the actor's process
        wait_for(lambda: all(r.steps > 3 for r in fleet.robots.values()), 60)
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: fleet.loop.inference_holds > 0, 30)  # every robot of the version holds meanwhile
        with fleet.lock:
            held = {r.id: r.steps for r in fleet.robots.values()}
        assert inference.failures >= 1
        time.sleep(0.3)
        with fleet.lock:
            if fleet.loop.inference_holds:  # still down: no robot moved on its policy
                assert {r.id: r.steps for r in fleet.robots.values()} == held
        wait_for(lambda: all(r.steps > held[r.id] + 3 for r in fleet.robots.values()), 120)  # resumed
        assert ray_local.get(inference.handle.pid.remote(), timeout=60) != pid  # on the restarted actor
        assert all(r.mode != "faulted" and r.restarts == 0 for r in fleet.robots.values())
    with sessions() as s:  # the episodes in progress were recorded through the outage and closed at the stop
        outcomes = [e.outcome for e in s.query(EpisodeRecord).all()]
    assert outcomes and "faulted" not in outcomes


def test_every_applied_teleop_step_survives_a_kill_right_after_it(tmp_path):
    """The durability bound (docs/service.md), end to end: a step the robot's view shows as applied is in
    the takeover's file even when the server is killed at once. (Here the denoising field makes each
    step big enough to fill a chunk every second step, so the old flush policy kept most steps too;
    ``tests/storage/test_storage.py`` tells the policies apart on small steps.)"""
    config, settings, sessions, h = _asking_config(tmp_path, 'console = false\n[workers]\nkind = "in-process"\n')
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = _serve(config, port)
    try:
        _ready(url)
        sent = _drive(url + "/api/v1", h, 30, 0.0005)
        proc.send_signal(signal.SIGKILL)  # at once: the last step was applied a tick ago at most
        assert proc.wait(timeout=60) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
    _restart_to_recover(config, port, url)  # its start rewrites the segment the kill left open
    with sessions() as s:
        row = s.query(SegmentRecord).one()
        assert row.status == "recovered"
        path = in_store(settings.data_dir, row.path)
    commands = [m["command"]["delta_pos"] for topic, m in _standard_read(path) if topic == "/takeover/step"]
    assert commands == sent, (len(commands), len(sent))  # all 30, in order: none lost

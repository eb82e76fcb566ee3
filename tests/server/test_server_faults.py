"""Faults: a worker that dies, a server killed mid-takeover, and a clean SIGTERM."""

import multiprocessing
import os
import signal
import subprocess
import sys
import time

import httpx
import pytest

from server.auth import create_token
from server.db import SegmentRecord, make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for


def _worker_pid(name):
    """The live worker process of that name among this process's children (the service runs here)."""
    alive = [p for p in multiprocessing.active_children() if p.name == name and p.is_alive()]
    return alive[-1].pid if alive else None


def _sessions(settings):
    migrate(settings.db_url)
    return session_factory(make_engine(settings.db_url))


def test_a_dead_worker_faults_restarts_and_closes_its_segment(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        control_hz=20,
        budget_steps=100,
    )
    sessions = _sessions(settings)
    token = create_token(sessions, "op", "operator")
    h = {"Authorization": f"Bearer {token}"}
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        wait_for(lambda: httpx.get(api + "/robots/0", headers=h).json()["mode"] == "waiting")
        assert httpx.post(api + "/robots/0/claim", headers=h).status_code == 200
        pid = _worker_pid("robot-0")  # the service's worker process, as the OS shows it
        os.kill(pid, signal.SIGKILL)
        robot = wait_for(lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] == "faulted" and r)
        assert "exited" in robot["fault"] or "broke" in robot["fault"]
        with sessions() as s:
            rows = s.query(SegmentRecord).all()
            assert rows and all(r.status == "closed" for r in rows)
        # restarted with backoff, then the policy runs (and, with this threshold, asks) again
        again = wait_for(
            lambda: (r := httpx.get(api + "/robots/0", headers=h).json())["mode"] in ("autonomous", "waiting") and r, 30
        )
        restarted = wait_for(lambda: _worker_pid("robot-0"))
        assert again["restarts"] == 1 and restarted != pid
        # the restarted physics runs below the control loop again
        assert wait_for(lambda: os.getpriority(os.PRIO_PROCESS, restarted) == settings.worker_niceness)
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


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGKILL, "recovered"), (signal.SIGTERM, "closed")])
def test_a_takeover_survives_the_server_stopping(tmp_path, sig, status):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)
    config = tmp_path / "fleet.toml"
    config.write_text(
        f'data_dir = "{tmp_path / "var"}"\ncontrol_hz = 20\nbudget_steps = 100\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    settings = Settings.load(config)
    sessions = _sessions(settings)
    h = {"Authorization": f"Bearer {create_token(sessions, 'op', 'operator')}"}
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = _serve(config, port)
    try:
        _ready(url)
        wait_for(lambda: httpx.get(url + "/api/v1/robots/0", headers=h).json()["mode"] == "waiting")
        assert httpx.post(url + "/api/v1/robots/0/claim", headers=h).status_code == 200
        cmd = {"delta_pos": [0, 0, 0.01], "gripper": -1}
        for _ in range(3):
            httpx.post(url + "/api/v1/robots/0/command", json=cmd, headers=h)
            time.sleep(0.4)  # > the 1 s flush interval in total
        time.sleep(1.2)
        proc.send_signal(sig)
        # the process ends by the signal (uvicorn re-raises SIGTERM once its graceful shutdown is done)
        assert proc.wait(timeout=60) == -sig
    finally:
        if proc.poll() is None:
            proc.kill()
    if sig == signal.SIGKILL:
        with sessions() as s:
            assert s.query(SegmentRecord).one().status == "open"  # the crash left it open
        proc = _serve(config, port)  # the restart recovers it
        try:
            _ready(url)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
    with sessions() as s:
        row = s.query(SegmentRecord).one()
        assert row.status == status and row.steps >= 1


def test_whole_episodes_are_recorded_when_asked(tmp_path):
    from storage.episodes import read_episode

    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1e9)  # never asks: autonomous
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        control_hz=0,
        record_episodes=True,
    )
    sessions = _sessions(settings)
    h = {"Authorization": f"Bearer {create_token(sessions, 'viewer', 'viewer')}"}
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        done = wait_for(lambda: [e for e in httpx.get(api + "/episodes", headers=h).json() if e["outcome"]], 120)
    from server.db import EpisodeRecord

    with sessions() as s:
        row = s.get(EpisodeRecord, done[-1]["id"])
    ep = read_episode(row.path)
    assert len(ep) == row.steps == done[-1]["steps"] and ep.outcome is not None
    assert set(ep.sources) == {"policy"}

"""The fleet service on a real uvicorn server on 127.0.0.1, with a small fleet and tiny policies."""

import json
import math
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from policy.checkpoint import load_policy
from policy.signals import make_signal, save_signal
from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from sim.registry import make_task
from storage.segments import read_segment
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("svc")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=-1.0)  # every robot asks at once
    shadow = make_signal("output-variance", load_policy(policy)[0], {"num_samples": 8})
    shadow.calibration = {"threshold": 1.0, "quantile": 0.95, "samples": 0}  # scored, never drives
    save_signal(shadow, policy)
    settings = Settings(
        data_dir=root / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=2, policy=policy)],
        queue={"lease_seconds": 5.0},  # a claim outlives a loaded machine's few requests
        # robots ask again at once after a hand-back: each test finds them waiting and held
        controller={"budget": 3, "cooldown": 0, "shadow_signals": ["output-variance", "random"]},
        control_hz=20,
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator", "admin")}
    tokens["operator2"] = create_token(sessions, "operator-2", "operator")
    with Service(settings) as svc:
        svc.tokens = tokens
        yield svc


def _h(svc, who):
    return {"Authorization": f"Bearer {svc.tokens[who]}"}


def _robot(svc, rid):
    return httpx.get(f"{svc.url}/api/v1/robots/{rid}", headers=_h(svc, "viewer")).json()


def test_auth_needs_a_token_and_the_right_role(service):
    api = service.url + "/api/v1"
    assert httpx.get(service.url + "/healthz").status_code == 200
    assert httpx.get(api + "/robots").status_code == 401
    assert httpx.get(api + "/robots", headers={"Authorization": "Bearer nope"}).status_code == 401
    assert httpx.get(api + "/robots", headers=_h(service, "viewer")).status_code == 200
    assert httpx.post(api + "/robots/0/claim", headers=_h(service, "viewer")).status_code == 403
    assert httpx.post(api + "/robots/0/pause", headers=_h(service, "operator")).status_code == 403
    ws = service.url.replace("http", "ws") + "/api/v1/robots/0/teleop"
    for headers in ({}, {"Authorization": "Bearer nope"}):
        with pytest.raises(InvalidStatus) as denied:
            connect(ws, additional_headers=headers)
        assert denied.value.response.status_code == 401
    with connect(ws, additional_headers=_h(service, "viewer")) as conn:
        assert "state" in json.loads(conn.recv(timeout=10))
        conn.send('{"delta_pos": [0, 0, 0.01], "gripper": -1}')
        replies = [json.loads(conn.recv(timeout=10)) for _ in range(5)]
        assert any(r.get("status") == 403 for r in replies)


def test_takeover_round_trip_records_a_segment(service):
    api, op = service.url + "/api/v1", _h(service, "operator")
    wait_for(lambda: _robot(service, 0)["mode"] == "waiting")
    queue = httpx.get(api + "/assistance", headers=_h(service, "viewer")).json()
    [request] = [r for r in queue if r["robot_id"] == 0]
    assert request["reason"].startswith("choice-stall: the policy has a choice of which way to go")  # its own words
    before = _robot(service, 0)
    claim = httpx.post(api + "/robots/0/claim", headers=op)
    assert claim.status_code == 200, claim.text
    assert _robot(service, 0)["mode"] == "teleop"
    # a second claimant and a non-holder's command get 409 and change nothing
    assert httpx.post(api + "/robots/0/claim", headers=_h(service, "operator2")).status_code == 409
    cmd = {"delta_pos": [0.0, 0.0, 0.01], "delta_rot": [0, 0, 0], "gripper": -1.0}
    assert httpx.post(api + "/robots/0/command", json=cmd, headers=_h(service, "operator2")).status_code == 409
    # bad commands: 422 with a message, nothing changes
    for bad, msg in (
        ({"delta_pos": [math.nan, 0, 0], "gripper": -1}, "NaN"),
        ({"delta_pos": [0.5, 0, 0], "gripper": -1}, "less than or equal to 0.1"),  # each component, as the schema
        ({"delta_pos": [0, 0, 0], "delta_rot": [0, -0.6, 0], "gripper": -1}, "greater than or equal to -0.5"),
        ({"delta_pos": [0, 0], "gripper": -1}, "3 components"),
        ({"delta_pos": [0, 0, 0], "gripper": 3}, "less than or equal"),
        ({"delta_pos": [0, 0, 0], "gripper": False}, "not true or false"),  # a JSON bool is not a number
        ({"delta_pos": [True, 0, 0], "gripper": -1}, "not true or false"),
    ):
        r = httpx.post(
            api + "/robots/0/command",
            content=json.dumps(bad),
            headers=op | {"content-type": "application/json"},
        )
        assert r.status_code == 422 and msg in r.text, r.text
    assert httpx.post(api + "/robots/99/command", json=cmd, headers=op).status_code == 404
    assert _robot(service, 0)["mode"] == "teleop"
    start = _robot(service, 0)
    z0 = start["pose"]["position"][2]
    for _ in range(3):  # the budget: 3 operator steps, then the policy is back
        assert httpx.post(api + "/robots/0/command", json=cmd, headers=op).status_code == 200
        time.sleep(0.15)
    wait_for(lambda: _robot(service, 0)["assisted_steps"] >= 3)
    seg = wait_for(
        lambda: [
            s
            for s in httpx.get(api + "/segments?robot_id=0", headers=_h(service, "viewer")).json()
            if s["status"] == "closed"
        ]
    )[0]
    assert seg["steps"] == 3 and seg["operator"] == "operator-1"
    # the request it answered, in the queue's numbers, and the paper's U when the robot asked
    asked = ("signal", "score", "threshold", "reason")
    assert [seg[k] for k in asked] == [request[k] for k in asked] and seg["signal"] == "choice-stall"
    assert isinstance(seg["paper_u"], float)
    assert seg["started_at"].endswith(("+00:00", "Z"))  # times carry their zone
    data = httpx.get(f"{api}/segments/{seg['id']}/mcap", headers=_h(service, "viewer"))
    assert data.status_code == 200
    path = service.settings.data_dir / "downloaded.mcap"
    path.write_bytes(data.content)
    segment = read_segment(path)
    obs, labels = segment.labels()
    assert obs.shape[0] == labels.shape[0] == 3 and np.isfinite(labels).all()
    assert segment.meta["robot"] == 0 and segment.end["status"] == "closed"
    assert segment.request["reason"] == request["reason"] and segment.request["paper_u"] == seg["paper_u"]
    # the file names its observation's channels (what fine-tuning checks against the policy's layout)
    lift = make_task("lift-cube").obs_spec
    assert segment.meta["obs_labels"] == lift.labels() and obs.shape[1] == lift.dim
    assert [s.command["delta_pos"] for s in segment.steps] == [[0.0, 0.0, 0.01]] * 3
    # every score but the denoising U (recorded on its own): the asking signal (the default) and the shadows
    assert all(set(s.shadow) == {"choice-stall", "output-variance", "random"} for s in segment.steps)
    fields = segment.fields
    assert len(fields) == 3 and len(fields[0]["entities"][0]["arrows"]) > 0  # the vector field, for Foxglove
    assert before["episode_id"] == start["episode_id"]
    # the operator's three 1 cm steps up moved the end effector up (the arm lags its targets)
    assert _robot(service, 0)["pose"]["position"][2] > z0 + 0.005


def test_a_waiting_robot_says_why_in_the_numbers_the_queue_uses(service):
    """``GET /robots/{id}`` of a waiting robot: its asking signal's name, score, threshold and reason are
    its queue entry's, and so are the old ``uncertainty`` and ``threshold``; the paper's U and threshold
    are ``paper``, apart."""
    api, viewer = service.url + "/api/v1", _h(service, "viewer")

    def a_waiting_robot():  # read before the queue: a robot shown waiting has its request open
        waiting = [r["id"] for r in httpx.get(api + "/robots", headers=viewer).json() if r["mode"] == "waiting"]
        return waiting[:1]

    [rid] = wait_for(a_waiting_robot)
    queue = httpx.get(api + "/assistance", headers=viewer).json()
    [request] = [r for r in queue if r["robot_id"] == rid]
    robot = _robot(service, rid)
    assert robot["mode"] == "waiting" and request["holder"] is None  # nobody took it meanwhile
    asking = robot["asking"]
    assert (asking["score"], asking["threshold"], asking["reason"]) == (
        request["uncertainty"],
        request["threshold"],
        request["reason"],
    )
    assert (robot["uncertainty"], robot["threshold"]) == (request["score"], request["threshold"])
    assert asking["signal"] == request["signal"] == "choice-stall" and asking["reason"].startswith("choice-stall: ")
    assert isinstance(asking["asked_at_step"], int) and asking["wants_help"] is True
    # the paper's denoising metric, a field of its own: its U (the last denoising result's) and threshold (-1)
    assert robot["paper"] == {"U": robot["last_uncertainty"]["U"], "threshold": -1.0}
    assert robot["paper"]["U"] == robot["u_history"][-1] and robot["threshold"] == 1.0  # choice-stall's
    assert len(robot["score_history"]) == len(robot["u_history"])
    # the list and the operator view say the same
    [listed] = [r for r in httpx.get(api + "/robots", headers=viewer).json() if r["id"] == rid]
    view = httpx.get(f"{api}/robots/{rid}/view", headers=viewer).json()
    assert listed["asking"] == view["asking"] == asking


def test_an_expired_lease_requeues_the_request(service):
    api, op = service.url + "/api/v1", _h(service, "operator")
    wait_for(lambda: _robot(service, 1)["mode"] == "waiting")
    assert httpx.post(api + "/robots/1/claim", headers=op).status_code == 200
    assert _robot(service, 1)["mode"] == "teleop"
    wait_for(lambda: _robot(service, 1)["mode"] == "waiting", timeout=30)  # no heartbeat for 5 s
    req = [r for r in httpx.get(api + "/assistance", headers=_h(service, "viewer")).json() if r["robot_id"] == 1][0]
    assert req["holder"] is None
    # now anyone may claim it
    assert httpx.post(api + "/robots/1/claim", headers=_h(service, "operator2")).status_code == 200
    assert httpx.post(api + "/robots/1/release", headers=_h(service, "operator2")).status_code == 200


def test_the_operator_bot_completes_takeovers_through_the_api(service):
    from client.operator_bot import OperatorBot

    migrate(service.settings.db_url)
    token = create_token(session_factory(make_engine(service.settings.db_url)), "bot", "operator")
    bot = OperatorBot(service.url, token)
    started = time.monotonic()
    try:
        bot.run(max_takeovers=2)
    finally:
        bot.close()
    bot_seconds = time.monotonic() - started
    assert bot.takeovers == 2 and bot.commands >= 2
    api = service.url + "/api/v1"
    segs = wait_for(
        lambda: [
            s
            for s in httpx.get(api + "/segments?operator=bot", headers=_h(service, "viewer")).json()
            if s["status"] == "closed"
        ]
    )
    assert segs and all(s["steps"] >= 1 for s in segs)
    data = httpx.get(f"{api}/segments/{segs[0]['id']}/mcap", headers=_h(service, "viewer")).content
    path = service.settings.data_dir / "bot-segment.mcap"
    path.write_bytes(data)
    segment = read_segment(path)
    assert segment.meta["operator"] == "bot" and len(segment.steps) == segs[0]["steps"]
    metrics = httpx.get(api + "/metrics/fleet", headers=_h(service, "viewer")).json()
    assert metrics["queue_wait_p50_s"] is not None and metrics["operator_busy_s"]["bot"] > 0
    # the claim's answer is computed just after the claim: its wait is the queue's own, plus a moment
    assert len(bot.waits) == 2 and metrics["queue_wait_max_s"] >= max(w for _, w in bot.waits) - 0.1
    # in control and idle since its first claim add up to no more than the time the bot has been around
    assert metrics["operator_idle_s"]["bot"] + metrics["operator_busy_s"]["bot"] <= bot_seconds + 1.0


def test_admin_pauses_resumes_and_resets_a_robot(service):
    api, admin = service.url + "/api/v1", _h(service, "admin")
    episode = _robot(service, 1)["episode_id"]
    r = httpx.post(api + "/robots/1/pause", headers=admin)
    assert r.status_code == 200 and r.json()["mode"] == "paused"
    time.sleep(0.5)
    pose = _robot(service, 1)["pose"]["position"]
    time.sleep(0.5)
    assert _robot(service, 1)["mode"] == "paused"
    assert np.allclose(_robot(service, 1)["pose"]["position"], pose, atol=2e-3)  # holds, no drift
    assert httpx.post(api + "/robots/1/pause", headers=admin).json()["mode"] == "paused"  # idempotent
    assert httpx.post(api + "/robots/1/resume", headers=admin).status_code == 200
    again = httpx.post(api + "/robots/1/resume", headers=admin)
    assert again.status_code == 409 and "not paused" in again.json()["detail"]
    assert httpx.post(api + "/robots/42/reset", headers=admin).status_code == 404
    assert httpx.post(api + "/robots/1/reset", headers=admin).status_code == 200
    assert wait_for(lambda: _robot(service, 1)["episode_id"] != episode)


def test_an_operator_streams_commands_over_the_websocket(service):
    api, op = service.url + "/api/v1", _h(service, "operator")
    wait_for(lambda: _robot(service, 0)["mode"] == "waiting")
    assert httpx.post(api + "/robots/0/claim", headers=op).status_code == 200
    before = _robot(service, 0)["assisted_steps"]
    ws = service.url.replace("http", "ws") + "/api/v1/robots/0/teleop"
    with connect(ws, additional_headers=op) as conn:
        conn.send(json.dumps({"delta_pos": [0, 0, 0.01], "gripper": -1}))
        conn.send(json.dumps({"delta_pos": [float("nan"), 0, 0], "gripper": -1}))
        replies = []
        while len([r for r in replies if "state" not in r]) < 2:
            replies.append(json.loads(conn.recv(timeout=10)))
        answers = [r for r in replies if "state" not in r]
        assert answers[0] == {"accepted": True, "pending": 1} and answers[1]["status"] == 422
    wait_for(lambda: _robot(service, 0)["assisted_steps"] > before)
    httpx.post(api + "/robots/0/release", headers=op)


def test_oversized_bodies_are_refused_with_or_without_a_length(service):
    api, op = service.url + "/api/v1", _h(service, "operator")
    big = b'{"delta_pos": [0, 0, 0], "gripper": -1, "pad": "' + b"x" * 70_000 + b'"}'
    r = httpx.post(api + "/robots/0/command", content=big, headers=op | {"content-type": "application/json"})
    assert r.status_code == 413

    def chunks():
        for i in range(0, len(big), 4096):
            yield big[i : i + 4096]

    r = httpx.post(api + "/robots/0/command", content=chunks(), headers=op | {"content-type": "application/json"})
    assert r.status_code == 413
    # a small chunked body still reaches the API, which answers for the unknown robot
    small = json.dumps({"delta_pos": [0, 0, 0], "gripper": -1}).encode()
    r = httpx.post(api + "/robots/99/command", content=iter([small]), headers=op | {"content-type": "application/json"})
    assert r.status_code == 404 and "no robot 99" in r.text


def test_a_shadow_run_scores_every_step_and_never_asks(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # every step is over it
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=2, policy=policy)],
        control_hz=20,
        controller={"assistance": False},
    )
    migrate(settings.db_url)
    token = create_token(session_factory(make_engine(settings.db_url)), "viewer", "viewer")
    h = {"Authorization": f"Bearer {token}"}
    with Service(settings) as svc:
        api = svc.url + "/api/v1"

        def stepped():
            rs = httpx.get(api + "/robots", headers=h).json()
            return rs if all(r["episode_step"] >= 5 for r in rs) else None

        robots = wait_for(stepped)
        assert all(r["mode"] == "autonomous" for r in robots)
        assert httpx.get(api + "/assistance", headers=h).json() == []
        for r in robots:
            detail = httpx.get(f"{api}/robots/{r['id']}", headers=h).json()
            assert len(detail["u_history"]) >= 5 and all(math.isfinite(u) and u >= 0 for u in detail["u_history"])


def test_the_operator_bot_survives_an_episode_that_ends_mid_takeover(service):
    from client.operator_bot import OperatorBot
    from sim.view import OperatorView, ViewUnavailable

    with pytest.raises(ViewUnavailable):  # the view of a robot with no scene to drive
        OperatorView.from_api(
            {"robot_id": 0, "task": "lift-cube", "mode": "teleop", "pose": None, "gripper": None, "goal": {}}
        )
    migrate(service.settings.db_url)
    token = create_token(session_factory(make_engine(service.settings.db_url)), "bot-reset", "operator")
    api = service.url + "/api/v1"
    resets = []

    class ResettingBot(OperatorBot):
        """Has an admin reset its robot right after its first claim: that episode ends under its hands."""

        def _get(self, path):
            if path.endswith("/view") and not resets:
                rid = int(path.split("/")[2])
                assert httpx.post(f"{api}/robots/{rid}/reset", headers=_h(service, "admin")).status_code == 200
                resets.append(rid)
            return super()._get(path)

    bot = ResettingBot(service.url, token)
    try:
        bot.run(max_takeovers=3)
    finally:
        bot.close()
    assert resets and bot.takeovers == 3 and bot.errors == 0
    segs = httpx.get(api + "/segments?operator=bot-reset", headers=_h(service, "viewer")).json()
    first = min(segs, key=lambda s: s["id"])
    assert first["ended_by"] == "reset" and first["robot_id"] == resets[0]
    ends = [(s["id"], s["robot_id"], s["ended_by"], s["steps"]) for s in segs]
    assert all(s["ended_by"] in ("hand-back", "reset") for s in segs), ends

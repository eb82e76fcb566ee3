"""``hitl operator-bot`` against a real service on 127.0.0.1: it hands back once the object is held, and
gives up where the in-process operator's episodes stop."""

import httpx
import numpy as np

from client.operator_bot import OperatorBot, overtime
from policy.lockstep import OVERTIME
from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from storage.segments import read_segment
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for

OBJECT_Z = 13  # lift observation: eef_pos 3, eef_rot6d 6, gripper_qpos 2, then object_pos


def test_the_bot_hands_back_once_the_object_is_held(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # the robot asks at once
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        controller={
            "hand_back": "continuous",
            "cooldown": 100_000,
        },  # only the operator hands back; no new request this episode
        control_hz=40,
    )
    migrate(settings.db_url)
    token = create_token(session_factory(make_engine(settings.db_url)), "bot", "operator")
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        viewer = {"Authorization": f"Bearer {token}"}
        wait_for(lambda: httpx.get(api + "/robots/0", headers=viewer).json()["mode"] == "waiting")
        episode = httpx.get(api + "/robots/0", headers=viewer).json()["episode_id"]
        assert httpx.get(api + "/robots/0/view", headers=viewer).json()["horizon"] == 150  # lift's
        bot = OperatorBot(svc.url, token, hands_back_when_held=True)
        try:
            bot.run(max_takeovers=1)
        finally:
            bot.close()
        assert bot.takeovers == 1 and bot.commands > 10
        robot = httpx.get(api + "/robots/0", headers=viewer).json()
        # handed back mid-episode (an operator who drives on lifts the cube to success: a new episode)
        assert robot["mode"] == "autonomous" and robot["episode_id"] == episode
        seg = wait_for(
            lambda: [s for s in httpx.get(api + "/segments", headers=viewer).json() if s["status"] == "closed"]
        )
        path = tmp_path / "segment.mcap"
        path.write_bytes(httpx.get(f"{api}/segments/{seg[0]['id']}/mcap", headers=viewer).content)
        segment = read_segment(path)
        obs, _ = segment.labels()
    assert len(segment.steps) == bot.commands
    # it gave the robot back holding the cube: gripper closed on the last steps, the cube on its way up
    assert segment.steps[-1].command["gripper"] > 0
    assert 0.004 < obs[-1, OBJECT_Z] - obs[0, OBJECT_Z] < 0.02
    assert np.isfinite(obs).all()


def test_the_bot_gives_up_where_the_in_process_operators_episodes_stop():
    """At ``OVERTIME`` horizons of the episode's clock, as ``policy.lockstep`` stops an episode; the
    steps a request waited in the queue (holds: ``step`` counts them, ``clock`` does not) never make it
    give up; a view without a horizon or a clock (an older service) never does either."""
    assert not overtime({"clock": OVERTIME * 150 - 1, "horizon": 150})
    assert overtime({"clock": OVERTIME * 150, "horizon": 150})
    assert not overtime({"step": 10**6, "clock": 40, "horizon": 150})  # a long wait for the operator
    assert not overtime({"clock": 10**6, "horizon": None}) and not overtime({"clock": None, "horizon": 150})
    assert not overtime({"clock": 10**6}) and not overtime({"step": 10**6, "horizon": 150})

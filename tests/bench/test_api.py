"""``hitl bench api`` run tiny: the report's structure, and that the requests are made and counted
(never timing targets)."""

from bench.api import bench_api, plan_clients
from tests.helpers import tiny_policy_folder


def test_plan_splits_the_clients():
    assert plan_clients(50, 16) == {"websocket_streams": 5, "queue_cyclers": 2, "rest_pollers": 43}
    assert plan_clients(4, 2) == {"websocket_streams": 1, "queue_cyclers": 1, "rest_pollers": 2}
    assert plan_clients(4, 1) == {"websocket_streams": 1, "queue_cyclers": 0, "rest_pollers": 3}


def test_bench_api_tiny(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1.0)
    r = bench_api(
        robots=2, clients=4, seconds=3.0, idle_seconds=1.0, policy=policy, worker="in-process", progress=False
    )
    assert r["benchmark"] == "api"
    assert r["clients"] == {"rest_pollers": 2, "websocket_streams": 1, "queue_cyclers": 1}
    assert r["errors"] == {"total": 0, "by_kind": {}}
    assert r["server_log"]["warnings"] == 0

    req, lat = r["requests"], r["rest_latency"]
    assert req["rest"] > 0 and req["ws_commands"] > 0 and req["ws_state_messages"] > 0
    assert req["total"] == req["rest"] + req["ws_commands"]  # no request failed
    assert lat["count"] == req["rest"] == sum(k["count"] for k in lat["by_kind"].values())
    assert r["ws_command_ack_latency"]["count"] == req["ws_commands"]
    # two pollers cycle through the five read kinds; the cycler claims, commands, heartbeats, releases
    assert {"robots", "robot", "view", "queue", "metrics", "claim", "command", "heartbeat", "release"} <= set(
        lat["by_kind"]
    )
    assert lat["p50_ms"] <= lat["p99_ms"] <= lat["max_ms"]

    for phase in ("idle", "load"):
        c = r["control"][phase]
        assert c["action_period"]["count"] > 0 and c["env_steps_per_s"] > 0 and c["ticks_per_s"] > 0
    assert r["control"]["load"]["robots_by_mode_mean"].get("teleop", 0) > 0  # the stream's robot, at least

    goals = r["goals"]
    assert len(goals) == 3 and all(isinstance(g["met"], bool) for g in goals)
    assert goals[0]["met"] is False  # 4 clients and 2 robots are not the goal's scale, whatever the errors
    assert r["goals_met"] == all(g["met"] for g in goals)

"""``hitl bench loop`` on a tiny fleet: a real ``hitl serve`` process, the operator bot, the report."""

from types import SimpleNamespace

from bench.loop import loop_report, run_loop
from server.db import EpisodeRecord, make_engine, migrate, session_factory
from tests.helpers import tiny_policy_folder


def test_the_loop_bench_serves_a_fleet_with_the_bot_and_reports_from_the_database(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # asks at once
    config = tmp_path / "fleet.toml"
    config.write_text(
        'control_hz = 20\n[workers]\nkind = "in-process"\n[inference]\ntrace_policies = false\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    out = run_loop(4.0, "budgeted", config, tmp_path / "var", {"HITL_CONTROLLER__BUDGET": "2"}, progress=False)
    assert out["mode"] == "budgeted" and out["robots"] == 1
    assert out["bot"]["takeovers"] >= 1 and out["bot"]["commands"] >= 1 and out["bot"]["errors"] == 0
    assert out["takeovers_asked_by"].get("choice-stall", 0) >= 1  # the default signal asked, the bot answered
    assert set(out["takeovers_ended_by"]) <= {"hand-back", "service-stopped", "episode-ended"}
    assert out["episodes"] == sum(t["episodes"] for t in out["per_task"].values())
    assert out["interrupted"] >= 1  # the episode in progress when the service stopped
    assert out["longest_wait_s"] is not None and isinstance(out["unclaimed_at_end"], list)
    assert out["per_task"]["lift-cube"]["longest_wait_s"] is not None


def test_the_report_shows_the_longest_wait_and_a_robot_never_served(tmp_path):
    """The report from a database and the queue's snapshot alone: a robot still waiting at the end is
    listed with its age, and each task's longest wait comes from the bot's claims."""
    url = f"sqlite:///{tmp_path / 'hitl.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    with sessions() as s:
        s.add_all(
            [
                EpisodeRecord(robot_id=0, task="lift-hammer", seed=0, outcome="success"),
                EpisodeRecord(robot_id=1, task="open-drawer", seed=1, outcome=None),  # never served
            ]
        )
        s.commit()
    bot = SimpleNamespace(takeovers=2, commands=9, errors=0, waits=[(0, 1.5), (0, 4.0)])
    starved = {"robot_id": 1, "task": "open-drawer", "waited_s": 700.0, "reason": "spread score 0.65 over 0.5"}
    queue = {"longest_wait_s": 4.0, "unclaimed": [starved]}
    settings = SimpleNamespace(robots=[SimpleNamespace(count=2)])
    out = loop_report(sessions, settings, 10.0, "continuous", bot, queue=queue)
    assert out["longest_wait_s"] == 4.0 and out["unclaimed_at_end"] == [starved]
    assert out["per_task"]["lift-hammer"]["longest_wait_s"] == 4.0 and "open-drawer" not in out["per_task"]
    assert loop_report(sessions, settings, 10.0, "continuous", None)["longest_wait_s"] is None  # no snapshot

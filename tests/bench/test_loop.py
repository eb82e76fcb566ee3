"""``hitl bench loop`` on a tiny fleet: a real ``hitl serve`` process, the operator bot, the report."""

from bench.loop import run_loop
from tests.helpers import tiny_policy_folder


def test_the_loop_bench_serves_a_fleet_with_the_bot_and_reports_from_the_database(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # asks at once
    config = tmp_path / "fleet.toml"
    config.write_text(
        f'worker = "in-process"\ncontrol_hz = 20\ntrace_policies = false\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    out = run_loop(4.0, "budgeted", config, tmp_path / "var", {"HITL_BUDGET_STEPS": "2"}, progress=False)
    assert out["mode"] == "budgeted" and out["robots"] == 1
    assert out["bot"]["takeovers"] >= 1 and out["bot"]["commands"] >= 1 and out["bot"]["errors"] == 0
    assert out["takeovers_asked_by"].get("spread", 0) >= 1  # the default signal asked, the bot answered
    assert set(out["takeovers_ended_by"]) <= {"hand-back", "service-stopped", "episode-ended"}
    assert out["episodes"] == sum(t["episodes"] for t in out["per_task"].values())
    assert out["interrupted"] >= 1  # the episode in progress when the service stopped

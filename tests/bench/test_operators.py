"""``hitl bench operators``: the fleet's mix, the operator's pace, the figures of one size and the headline,
from records; and one tiny sweep through a real ``hitl serve`` with the bot at a person's pace."""

from types import SimpleNamespace

import pytest

from bench.operators import FleetMix, OperatorsPlan, Pace, keeps_up, robots_per_operator, run_operators, size_report
from client.operator_bot import HumanPace
from tests.helpers import tiny_policy_folder


def test_the_mix_refuses_shares_that_do_not_sum_to_one_and_unknown_tasks():
    with pytest.raises(ValueError, match="must sum to 1, got 0.9"):
        FleetMix.parse(["lift-cube=0.5", "cup-stack=0.4"])
    with pytest.raises(ValueError, match="unknown task 'lift-moon'"):
        FleetMix.parse(["lift-moon=1"])
    with pytest.raises(ValueError, match="positive"):
        FleetMix({"lift-cube": 1.2, "cup-stack": -0.2})
    with pytest.raises(ValueError, match="task=share"):
        FleetMix.parse(["lift-cube"])
    with pytest.raises(ValueError, match="twice"):
        FleetMix.parse(["lift-cube=0.5", "lift-cube=0.5"])
    assert FleetMix.parse(None).shares == {"lift-cube": 0.7, "lift-hammer": 0.1, "cup-stack": 0.1, "open-drawer": 0.1}


def test_the_mix_rounds_a_fleet_by_largest_remainder_and_every_size_adds_up():
    mix = FleetMix.parse(None)
    assert mix.counts(10) == {"lift-cube": 7, "lift-hammer": 1, "cup-stack": 1, "open-drawer": 1}
    assert mix.counts(5) == {"lift-cube": 4, "lift-hammer": 1}  # 3.5, 0.5, 0.5, 0.5: ties go to the first named
    assert mix.counts(15) == {"lift-cube": 11, "lift-hammer": 2, "cup-stack": 1, "open-drawer": 1}
    for n in range(1, 41):
        assert sum(mix.counts(n).values()) == n
    with pytest.raises(ValueError, match="at least one robot"):
        mix.counts(0)


def test_the_pace_is_counted_in_ticks_and_becomes_seconds_at_the_fleets_clock():
    assert Pace(10, 20, 30).seconds(5.0) == HumanPace(2.0, 4.0, 6.0)
    with pytest.raises(ValueError, match="whole number of ticks"):
        Pace(claim=-1)
    with pytest.raises(ValueError, match="finite number"):
        HumanPace(claim_s=float("nan"))


def test_a_plan_refuses_what_cannot_run(tmp_path):
    with pytest.raises(ValueError, match="fleet sizes"):
        OperatorsPlan(sizes=(0,))
    with pytest.raises(ValueError, match="unknown queue order"):
        OperatorsPlan(sizes=(2,), order="lifo")
    with pytest.raises(FileNotFoundError):
        OperatorsPlan(sizes=(2,), config=tmp_path / "missing.toml")


def _episode(task, outcome, steps):
    return SimpleNamespace(task=task, outcome=outcome, assisted_steps=steps)


def test_one_sizes_figures_from_records_and_the_headline_conditions():
    """Two lift-cube robots and one drawer robot for 100 s at 10 Hz: per task and overall success, waits in
    seconds and ticks with the unclaimed request counted at its age, ROHE, idle share, utilisation."""
    counts = {"lift-cube": 2, "open-drawer": 1}
    episodes = [_episode("lift-cube", "success", 0)] * 9 + [_episode("lift-cube", None, 0)]  # one still running
    episodes += [_episode("open-drawer", "success", 4)] * 3 + [_episode("open-drawer", "timeout", 8)]
    # the drawer's takeovers: one per episode that ended (4, 4, 4, 8 steps), one of the episode still running (6)
    segments = [SimpleNamespace(task="open-drawer", steps=n) for n in (4, 4, 4, 8, 6)]
    episodes += [_episode("open-drawer", None, 6)]
    task_of = {0: "lift-cube", 1: "lift-cube", 2: "open-drawer"}
    out = size_report(
        counts, episodes, segments, [(2, 1.0), (2, 2.0), (2, 3.0)], [(2, 4.0)], task_of, 100.0, 10.0, 30.0
    )
    lift, drawer = out["per_task"]["lift-cube"], out["per_task"]["open-drawer"]
    assert lift["episodes"] == 9 and lift["success_rate"] == 1.0 and lift["queue_wait"]["n"] == 0
    assert lift["rohe"] is None and lift["robot_idle"] == 0.0
    assert drawer["success_rate"] == 0.75 and drawer["takeovers"] == 5 and drawer["operator_steps"] == 26
    assert drawer["rohe"] == pytest.approx(3 / 26)  # the running episode's effort is charged too
    assert out["operator_steps"] == 26 and out["rohe"] == pytest.approx(12 / 26)
    assert drawer["queue_wait"]["max_s"] == 4.0 and drawer["queue_wait"]["max_ticks"] == 40.0
    assert drawer["queue_wait"]["p50_ticks"] == pytest.approx(25.0) and drawer["unclaimed_at_end"] == 1
    assert drawer["robot_idle"] == pytest.approx(10.0 / 100.0)
    assert out["success_rate"] == pytest.approx(12 / 13) and out["utilisation"] == pytest.approx(0.3)
    assert out["robot_idle"] == pytest.approx(10.0 / 300.0)
    out["clock"] = {"held_hz": 10.0, "kept_clock": True}
    assert not keeps_up(out, ["lift-cube", "open-drawer"])  # the drawer at 75%
    drawer["success_rate"] = 0.95
    assert keeps_up(out, ["lift-cube", "open-drawer"])
    assert not keeps_up(dict(out, clock={"held_hz": 8.0, "kept_clock": False}), ["lift-cube", "open-drawer"])
    assert not keeps_up(out, ["lift-cube", "open-drawer", "cup-stack"])  # a task of the mix with no robot
    slow = dict(out, queue_wait=dict(out["queue_wait"], max_ticks=301.0))
    assert not keeps_up(slow, ["lift-cube", "open-drawer"])
    assert robots_per_operator([out, dict(slow, robots=6)], ["lift-cube", "open-drawer"]) == 3


def test_a_tiny_sweep_through_the_service_with_the_bot_at_a_persons_pace(tmp_path):
    """Two robots whose policy asks at once, served for 100 ticks at 10 Hz by one operator who takes 2 ticks
    to claim and 3 more to switch robots: the claims waited, the operator was busy, the clock was measured."""
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # asks at every step
    config = tmp_path / "fleet.toml"
    config.write_text(
        'control_hz = 10\n[workers]\nkind = "in-process"\n[inference]\ntrace_policies = false\n'
        '[controller]\nhand_back = "budgeted"\nbudget = 2\n'
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    plan = OperatorsPlan(sizes=(2,), mix=FleetMix({"lift-cube": 1.0}), ticks=100, pace=Pace(2, 3, 4), config=config)
    out = run_operators(plan, tmp_path / "runs", progress=False)
    [size] = out["sizes"]
    assert size["robots"] == 2 and size["counts"] == {"lift-cube": 2}
    assert size["operator"]["claims"] >= 2 and size["operator"]["errors"] == 0
    assert size["queue_wait"]["n"] >= 2 and size["queue_wait"]["max_s"] >= 0.2  # the claim delay, at least
    assert 0 < size["utilisation"] <= 1.0  # busy time counted inside the run's window only
    assert size["clock"]["control_hz"] == 10 and not size["clock"]["slowed"] and size["clock"]["ticks"] > 0
    # each request got the budget's 2 operator steps (the last one maybe cut by the window's end): the
    # steps the store recorded, counted against the takeovers it recorded and the commands the bot sent
    lift = size["per_task"]["lift-cube"]
    assert lift["takeovers"] >= 2 and 2 * (lift["takeovers"] - 1) <= lift["operator_steps"] <= 2 * lift["takeovers"]
    assert lift["operator_steps"] <= size["operator"]["commands"]
    assert out["plan"]["pace_ticks"] == {"claim": 2, "switch": 3, "min_takeover": 4}
    # no lift-cube episode ends in 100 ticks (its horizon is 150 and 2-step help cannot lift the cube), so
    # no success rate exists to meet the goal: no size keeps up
    assert size["episodes"] == 0 and size["success_rate"] is None and not keeps_up(size, ["lift-cube"])
    assert out["robots_per_operator"] is None


def test_the_figure_draws_each_run_against_the_fleets_size(tmp_path):
    from bench.operators_figure import plot_operators

    def size(n, rate, p95):
        return {
            "robots": n,
            "per_task": {
                "lift-cube": {"success_rate": 1.0, "episodes": 9, "robots": 1},
                "open-drawer": {"success_rate": rate, "episodes": 2, "robots": 1},
            },
            "queue_wait": {"p95_ticks": p95, "max_ticks": 2 * p95},
        }

    report = {"plan": {"mix": {"lift-cube": 0.5, "open-drawer": 0.5}}, "sizes": [size(2, 1.0, 10), size(4, 0.9, 80)]}
    report["robots_per_operator"] = 2
    out = plot_operators([("today", report), ("before", dict(report, robots_per_operator=None))], tmp_path / "f.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_the_command_draws_an_earlier_report_beside_another_without_running(tmp_path, capsys):
    """``--from`` redraws a saved report (``make operators-figure``): nothing runs, nothing is overwritten."""
    import json

    from hitl.cli import main

    def report(rate):
        size = {
            "robots": 7,
            "per_task": {"lift-cube": {"success_rate": rate}},
            "queue_wait": {"p95_ticks": 50.0, "max_ticks": 90.0},
        }
        return {"plan": {"mix": {"lift-cube": 1.0}}, "sizes": [size], "robots_per_operator": 7}

    today, before = tmp_path / "today.json", tmp_path / "before.json"
    today.write_text(json.dumps(report(1.0)))
    before.write_text(json.dumps(report(0.5)))
    figure, out = tmp_path / "f.png", tmp_path / "not-written.json"
    args = ["bench", "operators", "--from", str(today), "--figure", str(figure), "--out", str(out)]
    assert main([*args, "--compare", f"before={before}"]) == 0
    assert json.loads(capsys.readouterr().out) == report(1.0)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not out.exists()

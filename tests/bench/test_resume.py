import json

import pytest

from bench.resume import AtStep, AtStepConfig, task_resume
from hitl.cli import main
from lab.assisted import AssistConfig, run_assisted
from tests.helpers import tiny_policy, tiny_policy_folder


def test_the_probe_asks_once_at_its_policy_step_and_the_operator_drives_the_budget():
    policy = tiny_policy("lift-cube")
    driver = AtStep(policy, AtStepConfig(at=5))
    eps, _ = run_assisted(policy, "lift-cube", [3], driver, config=AssistConfig(budget=3, n_envs=1), progress=False)
    (ep,) = eps
    assert ep.asked_at == [5] and ep.events == 1  # five policy steps, then the request
    assert ep.assisted_steps == 3 and ep.operator[6:9] == [True] * 3  # one hold step, then the operator
    assert not any(ep.operator[9:])  # the policy finishes alone
    with pytest.raises(ValueError, match="at must be"):
        AtStepConfig(at=-1)
    with pytest.raises(ValueError, match="takeover step"):
        task_resume(policy, "tiny", "lift-cube", [], [4], episodes=1, seed=0, progress=False)


def test_the_report_compares_each_takeover_with_the_same_seeds_alone(tmp_path, capsys):
    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1.0)
    out = tmp_path / "resume.json"
    argv = ["report", "resume", "--policy", str(folder), "--at", "0", "1000", "--budgets", "2", "--episodes", "2"]
    assert main([*argv, "--seed", "7", "--out", str(out), "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "| 0 | 2/2 |" in table and "| 1000 | 0/2 |" in table
    doc = json.loads(out.read_text())
    assert doc["command"].startswith("hitl ")  # the command line that made it (here, pytest's)
    (row,) = doc["tasks"]
    assert row["task"] == "lift-cube" and row["seeds"] == [7, 8]  # the policy's task
    assert row["alone"] == 0.0 and row["alone_steps"] == 150  # the untrained policy never lifts
    early, late = row["cells"]
    assert (early["at"], early["budget"], early["reached"], early["assisted_steps"]) == (0, 2, 2, 2.0)
    assert late["reached"] == 0 and late["assisted_steps"] == 0  # the episodes end before step 1000: nobody asks
    assert late["success_rate"] == row["alone"] and late["rescued"] == late["broke"] == 0
    with pytest.raises(SystemExit):
        main([*argv[:5], "-1"])  # a takeover step must be >= 0


def test_the_pregrasp_probe_hands_back_where_the_operator_placed_the_open_gripper(tmp_path, capsys):
    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1.0)
    out = tmp_path / "pregrasp.json"
    argv = ["report", "pregrasp", "--policy", str(folder), "--tasks", "lift-cube", "lift-hammer", "--episodes", "2"]
    assert main([*argv, "--seed", "4", "--out", str(out), "--quiet"]) == 0
    assert "| lift-hammer |" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    cube, hammer = doc["tasks"]
    assert (cube["task"], hammer["task"], cube["seeds"]) == ("lift-cube", "lift-hammer", [4, 5])
    for row in (cube, hammer):
        for ep in row["episodes"]:
            # the operator drove from the first step to the grasp (tens of steps), then the policy had the rest
            assert 10 < ep["operator_steps"] < 100 and ep["steps_after"] > 0
            assert not ep["success"] or ep["closed"]  # a lift needs the gripper closed
        assert row["alone"] == 0.0  # the untrained policy never lifts alone


def test_the_operator_hands_back_at_the_grasp_before_closing():
    policy = tiny_policy("lift-cube")
    cfg = AssistConfig(
        hand_back="continuous", return_after=None, operator_hands_back=True, operator_hands_back_at="placed", n_envs=1
    )
    (ep,), _ = run_assisted(policy, "lift-cube", [2], AtStep(policy, AtStepConfig(at=0)), config=cfg, progress=False)
    ran = [i for i, op in enumerate(ep.operator) if op]
    assert ran == list(range(1, ran[-1] + 1))  # one hold step, then the operator without a break
    assert all(a[9] < 0 for a, op in zip(ep.actions, ep.operator, strict=True) if op)  # it never closed
    with pytest.raises(ValueError, match="operator_hands_back_at"):
        AssistConfig(operator_hands_back_at="lifted")

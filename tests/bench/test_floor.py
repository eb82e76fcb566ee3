import json

import numpy as np
import pytest

from bench.floor import FloorRecipe, grid, reasks
from bench.hitl.run import BenchError
from bench.oracle import Oracle, OracleConfig, in_window, task_windows
from hitl.cli import main
from lab.assisted import AssistConfig, run_assisted
from tests.helpers import tiny_policy, tiny_policy_folder


def test_the_windows_read_the_scene_the_oracle_is_given(task_cache):
    lift = task_cache("lift-hammer")
    lift.reset(3)
    far = float(np.linalg.norm(lift.ee_pose()[0] - lift.privileged()["grasp_point"]))
    assert in_window("grasp", far + 0.01, lift, 0) and not in_window("grasp", far - 0.01, lift, 0)
    cup = task_cache("cup-stack")
    cup.reset(3)
    assert not in_window("insertion", 10.0, cup, 0)  # the green cup is not carried yet
    drawer = task_cache("open-drawer")
    drawer.reset(4)
    assert in_window("early", 2, drawer, 1) and not in_window("early", 2, drawer, 2)
    assert not in_window("astray", 10.0, drawer, 0)  # nothing is 10 m nearer than the intended handle
    assert task_windows("lift-nut") == ("grasp",) and task_windows("open-drawer") == ("early", "astray")


def test_the_oracle_asks_through_the_controller_and_stops_at_its_cap():
    policy = tiny_policy("open-drawer")
    early = Oracle(policy, OracleConfig(window="early", reach=2))
    cfg = AssistConfig(budget=4, n_envs=2)
    eps, _ = run_assisted(policy, "open-drawer", [4, 5], early, config=cfg, progress=False, on_reset=early.watch)
    for ep in eps:  # its first two policy steps ask, each followed by the 4-step budget
        assert ep.asked_at == [0, 5] and ep.assisted_steps == 8
    lift = tiny_policy("lift-cube")
    capped = Oracle(lift, OracleConfig(window="grasp", reach=10.0, requests=3))
    eps, _ = run_assisted(
        lift, "lift-cube", [7], capped, config=AssistConfig(budget=2, n_envs=1), progress=False, on_reset=capped.watch
    )
    assert eps[0].events == 3 and eps[0].assisted_steps == 6
    blind = Oracle(lift, OracleConfig(window="grasp", reach=10.0))  # never given the scene: never asks
    eps, _ = run_assisted(lift, "lift-cube", [7], blind, config=AssistConfig(n_envs=1), progress=False)
    assert eps[0].events == 0
    with pytest.raises(ValueError, match="window"):
        OracleConfig(window="anywhere")
    with pytest.raises(ValueError, match="requests"):
        OracleConfig(requests=0)


def test_a_request_soon_after_a_hand_back_counts_as_a_re_ask():
    # asked at 0: the operator drives 1-4, the policy is back at 5; 14 is its 10th step, 15 its 11th
    assert reasks([0, 14, 40], budget=4) == 1 and reasks([0, 15], budget=4) == 0 and reasks([], budget=4) == 0


def test_the_recipe_keeps_the_sweep_off_the_evaluation_seeds():
    policies = (("lift-hammer", "p"),)
    with pytest.raises(BenchError, match="overlap"):
        FloorRecipe(policies, ("lift-hammer",), seed=1000, dev_seed=1010)
    with pytest.raises(BenchError, match="operator"):
        FloorRecipe(policies, ("lift-hammer",), operator="psychic")
    with pytest.raises(BenchError, match="resume"):
        FloorRecipe(policies, ("lift-hammer",), resume="rewind")
    with pytest.raises(BenchError, match="no policy"):
        FloorRecipe(policies, ("cup-stack",))
    assert len(grid("lift-hammer")) == 12 and len(grid("open-drawer", quick=True)) == 2


def test_the_floor_runs_the_sweep_then_the_finalists_and_writes_its_table(tmp_path, capsys):
    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1.0)
    report = tmp_path / "page.md"
    report.write_text("# A page\n\nkept\n")
    argv = ["bench", "floor", "--tasks", "lift-hammer", "--policy", f"lift-hammer={folder}", "--quick"]
    argv += ["--episodes", "1", "--dev-episodes", "1", "--finalists", "1", "--jobs", "1"]
    argv += ["--cache", str(tmp_path / "cache"), "--report", str(report), "--json", "--quiet"]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    row = doc["tasks"]["lift-hammer"]
    (point,) = row["sweep"]
    assert point["oracle"]["window"] == "grasp" and point["oracle"]["requests"] is None
    # the untrained policy never lifts, so the operator does it all, 4 steps per request, and succeeds
    assert row["floor"] is not None and row["floor"]["eval"]["success_rate"] == 1.0
    assert row["floor"]["eval"]["assisted_steps"] == pytest.approx(4 * row["floor"]["eval"]["requests"])
    assert row["full_teleop"]["success_rate"] == 1.0 and row["paper_ratio"] == 0.22
    text = report.read_text()
    assert text.startswith("# A page\n\nkept\n") and "<!-- hitl-bench:floor:begin -->" in text
    assert "| **floor: assisted steps per episode** |" in text and "grasp 0.2 m, no cap" in text
    cached = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert main(argv) == 0 and sorted(p.name for p in (tmp_path / "cache").iterdir()) == cached  # read back

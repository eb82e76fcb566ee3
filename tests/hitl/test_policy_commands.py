"""``hitl train``, ``rollout``, ``assist`` and the commands that roll a policy out refuse, before any
simulation or training, a policy or data whose observation layout or chunking does not fit the task, and
say what differs."""

from __future__ import annotations

import numpy as np

from hitl.cli import main
from sim.registry import make_task
from storage import keys
from storage.episodes import EpisodeWriter
from tests.helpers import tiny_policy_folder

LIFT = make_task("lift-cube").obs_spec.labels()
CUP = make_task("cup-stack").obs_spec.labels()


def _demos(folder, labels: list[str], episodes: int = 3):
    rng = np.random.default_rng(0)
    for i in range(episodes):
        meta = {"task": "lift-cube", "seed": i, "obs_labels": labels}
        with EpisodeWriter(folder / f"lift-cube_seed{i:06d}.mcap", meta, object_names=[]) as w:
            for t in range(4):
                act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [-1.0]]
                w.write_step(
                    t, rng.normal(size=len(labels)), act, act[:3], [0, 0, 0, 1.0], 0.04, t == 3, keys.SOURCE_EXPERT
                )
            w.finish(True, 4, "success")
    return folder


def test_training_refuses_data_of_another_layout_and_a_chunking_longer_than_the_task(tmp_path, capsys):
    moved = LIFT[:11] + LIFT[23:] + LIFT[11:23]  # the same size: only the names tell
    data = _demos(tmp_path / "moved", moved)
    small = ["--steps", "1", "--batch-size", "4", "--network", "mlp", "--obs-encoder-dims", "8", "--quiet"]
    out = tmp_path / "policy"
    assert main(["train", "--task", "lift-cube", "--data", str(data), "--out", str(out), *small]) == 2
    err = capsys.readouterr().err
    assert f"3 episode(s) of {data} were recorded with another observation layout than task lift-cube's" in err
    assert "e.g. lift-cube_seed000000.mcap" in err and "(at channel 11: object_extent, not object_pos)" in err
    data = _demos(tmp_path / "fine", LIFT)
    chunky = [*small, "--action-horizon", "151"]
    assert main(["train", "--task", "lift-cube", "--data", str(data), "--out", str(out), *chunky]) == 2
    assert "its action_horizon of 151 steps is longer than task lift-cube's horizon of 150" in capsys.readouterr().err
    assert not out.exists()  # refused before training: nothing written


def test_commands_that_run_a_policy_on_a_task_refuse_one_trained_on_another_layout(tmp_path, capsys):
    policy = tiny_policy_folder(tmp_path / "cup", "cup-stack", 0.5, obs_labels=CUP)
    for command in (["rollout", "--episodes", "1"], ["assist", "--episodes", "1"]):
        assert main([*command, "--policy", str(policy), "--task", "lift-nut", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"hitl {command[0]}: error: policy {policy} cannot run task lift-nut: it was trained on")
        assert "missing green_pos, green_rot6d, red_pos_observed, green_to_eef_pos" in err
    for command in (
        ["calibrate", "--data", str(tmp_path / "nowhere"), "--task", "lift-nut"],
        ["plot", "uncertainty", "--task", "lift-nut"],
        ["report", "novelty", "--tasks", "cup-stack", "lift-nut"],
        ["report", "resume", "--task", "lift-nut", "--at", "3"],
        ["report", "separation", "--shift-tasks", "lift-nut"],
        ["bench", "signals", "--task", "lift-nut"],
    ):
        assert main([*command, "--policy", str(policy)]) == 2, command
        assert f"policy {policy} cannot run task lift-nut: it was trained on" in capsys.readouterr().err, command
    # an older policy (no layout recorded) is judged by its observation size
    old = tiny_policy_folder(tmp_path / "old", "cup-stack", 0.5)
    assert main(["rollout", "--policy", str(old), "--task", "lift-nut", "--episodes", "1", "--quiet"]) == 2
    assert f"it takes 30-dim observations (its config.json records no layout), task lift-nut gives {len(LIFT)}" in (
        capsys.readouterr().err
    )

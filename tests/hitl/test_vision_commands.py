"""A policy that sees, from demonstrations with frames to a rollout, through the commands a lab runs:
``hitl demos --images``, ``hitl train``, ``hitl calibrate``, ``hitl rollout`` (the renderer for real)."""

import json

from hitl.cli import main
from policy.checkpoint import load_policy
from sim.env import ROBOT_OBS
from storage.dataset import load_dataset


def test_demos_with_frames_train_a_policy_that_sees_and_runs_on_its_task(tmp_path, capsys):
    data, out = tmp_path / "demos", tmp_path / "eyes"
    assert main(["demos", "--task", "lift-cube", "--episodes", "2", "--images", "--out", str(data), "--quiet"]) == 0
    ds = load_dataset(data)
    assert [c["name"] for c in ds.cameras] == ["front", "wrist"] and ds.obs.shape[1] == ROBOT_OBS.dim
    assert json.loads((data / "recipe.json").read_text())["images"] is True
    small = ["--steps", "3", "--batch-size", "8", "--network", "mlp", "--image-channels", "8", "--quiet"]
    assert main(["train", "--task", "lift-cube", "--data", str(data), "--out", str(out), *small]) == 0
    policy, info = load_policy(out)
    assert [c.name for c in policy.config.cameras] == ["front", "wrist"] and info["obs_labels"] == ROBOT_OBS.labels()
    assert (out / "model.safetensors").stat().st_size < 10e6
    calibrate = ["calibrate", "--policy", str(out), "--data", str(data), "--samples", "16", "--rollouts", "0"]
    assert main([*calibrate, "--quiet"]) == 0
    assert json.loads((out / "calibration.json").read_text())["samples"] > 0
    capsys.readouterr()
    rollout = ["rollout", "--policy", str(out), "--task", "lift-hook", "--episodes", "1", "--samples", "16"]
    assert main([*rollout, "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["episodes"] == 1 and report["per_episode"][0]["steps"] > 0
    # a task that lacks its cameras is refused, naming them
    assert main(["rollout", "--policy", str(out), "--task", "open-drawer", "--episodes", "1", "--quiet"]) == 2
    assert "it sees camera 'front', which task open-drawer lacks" in capsys.readouterr().err

"""``hitl export lerobot`` and ``hitl import lerobot`` on a real demo run: recorded in the simulator,
exported, read by Hugging Face ``datasets`` (not our writer), imported back, and trained on."""

from __future__ import annotations

import json

import datasets
import numpy as np

from hitl.cli import main
from policy.checkpoint import load_policy
from sim.registry import make_task
from storage.episodes import read_episode


def test_a_demo_run_exports_loads_imports_and_trains(tmp_path, capsys):
    demos, root, back = tmp_path / "demos", tmp_path / "lerobot", tmp_path / "imported"
    assert main(["demos", "--task", "lift-cube", "--episodes", "2", "--out", str(demos), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["export", "lerobot", str(root), "--demos", str(demos), "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    originals = [read_episode(p) for p in sorted(demos.glob("*.mcap"))]
    assert report["episodes"] == 2 and report["frames"] == sum(len(e) for e in originals)
    assert report["tasks"] == ["Lift the cube 4 cm off the table"]

    files = sorted(str(p) for p in root.glob("data/chunk-*/file-*.parquet"))
    frames = datasets.load_dataset("parquet", data_files=files, split="train").with_format("numpy")[:]
    first = frames["episode_index"] == 0
    assert np.allclose(frames["observation.state"][first], originals[0].obs, atol=1e-6)
    assert np.allclose(frames["action"][first], originals[0].actions, atol=1e-6)
    assert frames["next.success"][first].tolist() == originals[0].success.tolist()
    assert not frames["intervention"].any()  # a scripted demonstration: no operator

    # a second export into the same folder is refused; the first stays whole
    assert main(["export", "lerobot", str(root), "--demos", str(demos), "--quiet"]) == 2
    assert "is not empty" in capsys.readouterr().err

    assert main(["import", "lerobot", str(root), str(back), "--task", "lift-cube", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 2
    small = ["--steps", "3", "--batch-size", "8", "--network", "mlp", "--obs-encoder-dims", "16", "--quiet"]
    out = tmp_path / "policy"
    assert main(["train", "--task", "lift-cube", "--data", str(back), "--out", str(out), *small]) == 0
    policy, doc = load_policy(out)
    assert policy.config.obs_dim == originals[0].obs.shape[1]
    assert doc["obs_labels"] == make_task("lift-cube").obs_spec.labels()  # the layout it was trained on
    assert sorted(doc["dataset"]["train_episodes"] + doc["dataset"]["val_episodes"]) == sorted(
        p.name for p in back.glob("*.mcap")
    )

    # the task's layout is checked: another task's observation is refused, naming the feature
    assert main(["import", "lerobot", str(root), str(tmp_path / "x"), "--task", "open-drawer", "--quiet"]) == 2
    err = capsys.readouterr().err
    lift_dim = make_task("lift-cube").obs_spec.dim
    assert (
        "does not fit task open-drawer" in err and f"observation.state: shape [{lift_dim}], the task's is [23]" in err
    )
    assert (
        "missing drawer_opening, handle_pos; extra object_pos, object_rot6d, object_to_eef_pos, object_extent, "
        "finger_rays" in err
    )
    assert not (tmp_path / "x").exists()

    # a policy is not run on a task whose observation it was not trained on, and the error names the channels
    assert main(["rollout", "--policy", str(out), "--task", "open-drawer", "--episodes", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hitl rollout: error: policy {out} cannot run task open-drawer: it was trained on")
    assert (
        "missing object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays; extra drawer_opening" in err
    )

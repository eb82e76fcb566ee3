"""The LeRobotDataset v3.0 export and import, checked with readers that are not our writer: Hugging Face
``datasets`` (what LeRobot loads the frames with), pandas and plain JSON, against the layout LeRobot
documents (meta/info.json, meta/stats.json, meta/tasks.parquet, meta/episodes/, data/chunk-*/file-*)."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import datasets
import numpy as np
import pandas as pd
import pytest

from sim.registry import make_task
from sim.spaces import ACTION_LABELS
from storage import keys
from storage.episodes import EpisodeWriter, read_episode
from storage.lerobot.attempts import TakeoverLabel, from_episode, from_folder
from storage.lerobot.layout import ExportError, write_dataset
from storage.lerobot.reader import LeRobotImportError, import_dataset

TASK = "lift-cube"
SPEC = make_task(TASK).obs_spec
FPS = 20


def _episode(path: Path, seed: int, steps: int, takeover: tuple[int, int, int] | None = None) -> Path:
    """A fleet-style episode: the policy drives, except the steps [a, b) of ``takeover`` (a, b, segment id),
    where an operator does; every policy step is scored."""
    rng = np.random.default_rng(seed)
    meta = {"task": TASK, "seed": seed, "obs_labels": SPEC.labels(), "action_labels": list(ACTION_LABELS)}
    with EpisodeWriter(path, meta) as w:
        for t in range(steps):
            operator = takeover is not None and takeover[0] <= t < takeover[1]
            act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [-1.0]]
            extras = {keys.STEP_POLICY_VERSION: 3}
            if operator:
                extras |= {
                    keys.STEP_COMMAND: {"delta_pos": [0.01, 0.0, -0.02], "delta_rot": [0.0, 0.0, 0.1], "gripper": 1.0},
                    keys.STEP_TAKEOVER: takeover[2],
                }
            else:
                extras |= {keys.STEP_SCORE: float(t) / steps, keys.STEP_THRESHOLD: 0.5}
            source = keys.SOURCE_OPERATOR if operator else keys.SOURCE_POLICY
            w.write_step(
                t, rng.normal(size=SPEC.dim), act, act[:3], [0, 0, 0, 1.0], 0.04, t == steps - 1, source, {}, extras
            )
        w.finish(True, steps, "success")
    return path


@pytest.fixture
def folder(tmp_path):
    out = tmp_path / "episodes"
    _episode(out / "a.mcap", 0, 9)
    _episode(out / "b.mcap", 1, 14, takeover=(4, 8, 7))
    _episode(out / "c.mcap", 2, 5)
    return out


def _load(root: Path) -> datasets.Dataset:
    files = sorted(str(p) for p in (root / "data").glob("chunk-*/file-*.parquet"))
    return datasets.load_dataset("parquet", data_files=files, split="train")


def _episodes_meta(root: Path) -> pd.DataFrame:
    return pd.concat(pd.read_parquet(p) for p in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet")))


def test_the_export_has_the_documented_layout_with_monotonic_indices_and_true_stats(folder, tmp_path):
    attempts = from_folder(folder)
    label = TakeoverLabel("good", True, "recovered the grasp", "alice", datetime(2026, 12, 1, tzinfo=UTC))
    attempts[1].takeovers[7] = label
    root = tmp_path / "ds"
    report = write_dataset(attempts, root, FPS, list(ACTION_LABELS), {TASK: "Lift the cube"}, progress=False)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (3, 28, 1) == (3, report.frames, 1)
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    feats = info["features"]
    for name in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert name in feats  # LeRobot's default features
    assert feats["observation.state"] == {"dtype": "float32", "shape": [SPEC.dim], "names": SPEC.labels()}
    assert feats["action"]["names"] == list(ACTION_LABELS)

    ds = _load(root)
    assert set(ds.column_names) == set(feats)  # every column a feature, every feature a column
    for name, f in feats.items():  # the parquet types are what info.json says
        hf = ds.features[name]
        if f["shape"] == [1]:
            assert hf.dtype == f["dtype"], name
        else:
            assert (hf.length, hf.feature.dtype) == (f["shape"][0], f["dtype"]), name
    frame = ds.with_format("numpy")[:]
    n = len(ds)
    assert (frame["index"] == np.arange(n)).all()
    assert (np.diff(frame["episode_index"]) >= 0).all() and set(frame["episode_index"]) == {0, 1, 2}
    meta = _episodes_meta(root)
    assert list(meta["episode_index"]) == [0, 1, 2] and list(meta["length"]) == [9, 14, 5]
    for _, ep in meta.iterrows():
        rows = frame["episode_index"] == ep["episode_index"]
        assert (np.flatnonzero(rows) == np.arange(ep["dataset_from_index"], ep["dataset_to_index"])).all()
        assert (frame["frame_index"][rows] == np.arange(ep["length"])).all()
        assert np.allclose(frame["timestamp"][rows], np.arange(ep["length"]) / FPS)
        assert frame["next.done"][rows].tolist() == [False] * (ep["length"] - 1) + [True]
        assert list(ep["tasks"]) == ["Lift the cube"]
        assert np.allclose(ep["stats/action/mean"], frame["action"][rows].mean(axis=0))
    tasks = pd.read_parquet(root / "meta" / "tasks.parquet")
    assert tasks.loc["Lift the cube", "task_index"] == 0 and (frame["task_index"] == 0).all()

    stats = json.loads((root / "meta" / "stats.json").read_text())
    assert set(stats) == set(feats)
    for name in ("observation.state", "action", "asking.score", "index"):
        x = np.asarray(frame[name], np.float64).reshape(n, -1)
        assert np.allclose(stats[name]["min"], x.min(0)) and np.allclose(stats[name]["max"], x.max(0))
        assert np.allclose(stats[name]["mean"], x.mean(0), atol=1e-6) and np.allclose(stats[name]["std"], x.std(0))
        assert np.allclose(stats[name]["q50"], np.quantile(x, 0.5, axis=0)) and stats[name]["count"] == [n]

    # the takeover inside its episode: operator frames marked, with the command, its id and its label
    ep1 = frame["episode_index"] == 1
    operator = frame["intervention"] & ep1
    assert np.flatnonzero(operator).tolist() == list(range(9 + 4, 9 + 8))
    assert (frame["action_source"][operator] == keys.SOURCES.index(keys.SOURCE_OPERATOR)).all()
    assert np.allclose(frame["operator.command"][operator], [0.01, 0.0, -0.02, 0.0, 0.0, 0.1, 1.0])
    assert (frame["operator.command"][~frame["intervention"]] == 0).all()
    assert (frame["takeover.id"][operator] == 7).all() and (frame["takeover.id"][~operator] == -1).all()
    assert (frame["takeover.label"][operator] == 1).all() and frame["takeover.discarded"][operator].all()
    assert not frame["asking.scored"][operator].any() and frame["asking.scored"][~frame["intervention"]].all()
    assert np.allclose(frame["asking.threshold"][frame["asking.scored"]], 0.5)
    assert (frame["policy_version"] == 3).all()
    takeovers = json.loads(meta.iloc[1]["hitl/takeovers"])
    assert takeovers == {"7": label.as_dict()} and takeovers["7"]["note"] == "recovered the grasp"


def test_files_rotate_and_chunks_fill_with_whole_episodes(folder, tmp_path):
    root = tmp_path / "ds"
    write_dataset(
        from_folder(folder), root, FPS, list(ACTION_LABELS), data_files_size_in_mb=1e-4, chunks_size=2, progress=False
    )
    files = sorted((root / "data").glob("chunk-*/file-*.parquet"))
    assert [p.relative_to(root / "data").as_posix() for p in files] == [
        "chunk-000/file-000.parquet",
        "chunk-000/file-001.parquet",
        "chunk-001/file-000.parquet",
    ]
    meta = _episodes_meta(root)
    for _, ep in meta.iterrows():  # each episode lies whole in the file its metadata names
        path = root / f"data/chunk-{ep['data/chunk_index']:03d}/file-{ep['data/file_index']:03d}.parquet"
        assert sorted(pd.read_parquet(path, columns=["episode_index"])["episode_index"].unique()) == [
            ep["episode_index"]
        ]
    assert (_load(root).with_format("numpy")[:]["index"] == np.arange(28)).all()


def test_bad_exports_are_refused_and_leave_nothing_behind(folder, tmp_path):
    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    with pytest.raises(ExportError, match="not empty"):
        write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    other = from_folder(folder)
    other[0].obs = other[0].obs[:, :5]
    with pytest.raises(ExportError, match="mixes observation/action sizes"):
        write_dataset(other, tmp_path / "mixed", FPS, list(ACTION_LABELS), progress=False)
    assert not (tmp_path / "mixed").exists() and not (tmp_path / "mixed.partial").exists()
    with pytest.raises(ExportError, match="nothing to export"):
        write_dataset([], tmp_path / "none", FPS, list(ACTION_LABELS), progress=False)


def _import(root, out, **kw):
    return import_dataset(root, out, TASK, SPEC.labels(), list(ACTION_LABELS), progress=False, **kw)


def test_an_exported_dataset_imports_back_to_the_same_episodes(folder, tmp_path):
    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    report = _import(root, tmp_path / "back")
    assert (report.episodes, report.frames, report.successes) == (3, 28, 3)
    for original, back in zip(sorted(folder.glob("*.mcap")), sorted((tmp_path / "back").glob("*.mcap")), strict=True):
        a, b = read_episode(original), read_episode(back)
        assert np.allclose(a.obs, b.obs, atol=1e-6) and np.allclose(a.actions, b.actions, atol=1e-6)
        assert np.allclose(a.ee_pose, b.ee_pose, atol=1e-6) and (a.success == b.success).all()
        assert a.sources == b.sources and b.meta["obs_labels"] == SPEC.labels() and b.outcome["success"]
    with pytest.raises(LeRobotImportError, match="already holds episodes"):
        _import(root, tmp_path / "back")


def _edit_info(root: Path, edit) -> None:
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    edit(info)
    path.write_text(json.dumps(info))


def test_an_incompatible_dataset_is_refused_naming_each_mismatched_feature(folder, tmp_path):
    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)

    def rename(info):
        info["features"]["observation.state"]["names"][0] = "joint_pos[0]"
        info["features"]["action"]["names"] = ["j0", "j1", "j2", "j3", "j4", "j5", "j6", "r0", "r1", "gripper"]
        del info["features"]["observation.ee_pose"]

    _edit_info(root, rename)
    with pytest.raises(LeRobotImportError) as err:
        _import(root, tmp_path / "out")
    message = str(err.value)
    assert "observation.state: missing eef_pos[0]; extra joint_pos[0]\n" in message
    assert "action: missing x, y, z, r00, r10, r20, r01, r11, r21; extra j0, j1, j2, j3, j4, j5, j6, r0, r1" in message
    assert "observation.ee_pose: missing" in message
    assert not (tmp_path / "out").exists()  # refused before anything was written
    # with a way to compute the pose from the state, the pose is not a problem; the names still are
    with pytest.raises(LeRobotImportError, match="extra joint_pos") as err:
        _import(root, tmp_path / "out", pose_from_state=SPEC.ee_pose)
    assert "ee_pose" not in str(err.value)
    _edit_info(root, lambda info: info["features"]["action"].update(shape=[7], names=None))
    with pytest.raises(LeRobotImportError, match=r"action: shape \[7\], the task's is \[10\]; its channels are not"):
        _import(root, tmp_path / "out")
    _edit_info(root, lambda info: info.update(codebase_version="v2.1"))
    with pytest.raises(LeRobotImportError, match="codebase_version v2.1"):
        _import(root, tmp_path / "out")
    with pytest.raises(LeRobotImportError, match="not a LeRobotDataset"):
        _import(tmp_path / "nowhere", tmp_path / "out")


def test_a_dataset_that_lacks_a_channel_of_the_task_is_refused_naming_it_and_writes_nothing(tmp_path):
    # a cup-stack dataset recorded before the task observed whether the red cup was visible
    task, cup = "cup-stack", make_task("cup-stack").obs_spec
    older = cup.labels()[:-1]
    demos = tmp_path / "episodes"
    rng = np.random.default_rng(0)
    for i in range(2):
        with EpisodeWriter(demos / f"e{i}.mcap", {"task": task, "seed": i, "obs_labels": older}) as w:
            for t in range(3):
                act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [-1.0]]
                w.write_step(t, rng.normal(size=len(older)), act, act[:3], [0, 0, 0, 1.0], 0.04, t == 2, "expert")
            w.finish(True, 3, "success")
    root = tmp_path / "ds"
    write_dataset(from_folder(demos), root, FPS, list(ACTION_LABELS), progress=False)
    out = tmp_path / "out"
    with pytest.raises(LeRobotImportError) as err:
        import_dataset(root, out, task, cup.labels(), list(ACTION_LABELS), cup.ee_pose, progress=False)
    assert str(err.value) == (
        f"{root} does not fit task cup-stack:\n  observation.state: shape [29], the task's is [30]; missing red_visible"
    )
    assert not out.exists()  # refused before anything was written
    # a dataset that does not name its channels: its size is what can be said, and the task's channels
    _edit_info(root, lambda info: info["features"]["observation.state"].update(names=None))
    with pytest.raises(
        LeRobotImportError, match=r"shape \[29\], the task's is \[30\]; its channels are not named; the task's"
    ) as err:
        import_dataset(root, out, task, cup.labels(), list(ACTION_LABELS), cup.ee_pose, progress=False)
    assert "red_observed_to_green_pos(3), red_visible]" in str(err.value) and not out.exists()


def test_a_dataset_without_ee_pose_gets_it_from_the_state(tmp_path):
    demos = tmp_path / "episodes"
    rng = np.random.default_rng(0)
    meta = {"task": TASK, "seed": 0, "obs_labels": SPEC.labels()}
    pos, quat = np.array([0.1, -0.05, 0.9]), np.array([0.0, 0.0, 0.38268343, 0.92387953])  # 45° about z
    obs = rng.normal(size=SPEC.dim)
    obs[SPEC.slices()["eef_pos"]] = pos
    from sim.rotations import quat_to_rot6d

    obs[SPEC.slices()["eef_rot6d"]] = quat_to_rot6d(quat)
    with EpisodeWriter(demos / "e.mcap", meta) as w:
        w.write_step(0, obs, np.r_[pos, [1, 0, 0, 0, 1, 0], [-1.0]], pos, quat, 0.04, True, keys.SOURCE_EXPERT)
        w.finish(True, 1, "success")
    root = tmp_path / "ds"
    write_dataset(from_folder(demos), root, FPS, list(ACTION_LABELS), progress=False)
    _edit_info(root, lambda info: info["features"].pop("observation.ee_pose"))
    _import(root, tmp_path / "back", pose_from_state=SPEC.ee_pose)
    back = read_episode(next((tmp_path / "back").glob("*.mcap")))
    assert np.allclose(back.ee_pose[0, :3], pos, atol=1e-6)
    assert np.isclose(abs(np.dot(back.ee_pose[0, 3:], quat)), 1.0, atol=1e-6)  # the same rotation


def test_an_episode_built_from_a_recording_keeps_what_the_fleet_knew(folder):
    a = from_episode(read_episode(folder / "b.mcap"), {7: TakeoverLabel("bad"), 99: TakeoverLabel("good")})
    assert set(a.takeovers) == {7}  # labels of takeovers that are not in the episode are not carried
    codes, discarded = a.label_codes()
    assert codes.tolist() == [0] * 4 + [-1] * 4 + [0] * 6 and not discarded.any()


def test_non_finite_values_are_refused_before_any_episode_is_written(folder, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    [path] = (root / "data").glob("chunk-*/file-*.parquet")
    table = pq.read_table(path)
    state = np.array(table.column("observation.state").to_pylist(), np.float32)
    state[-1, 0] = np.nan  # the last episode's last frame: the earlier episodes are fine
    column = pa.FixedSizeListArray.from_arrays(pa.array(state.reshape(-1)), state.shape[1])
    pq.write_table(table.set_column(0, "observation.state", column), path)
    with pytest.raises(LeRobotImportError, match=r"episode\(s\) \[2\] have non-finite"):
        _import(root, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def _seeing_folder(out: Path, episodes=(4, 6)) -> tuple[Path, dict]:
    """Demonstrations recorded for a policy that sees (the robot's own state and lift's two cameras)."""
    task = make_task(TASK, images=True)
    cams = [c.to_json() for c in task.cameras]
    shown = {}
    for e, steps in enumerate(episodes):
        rng = np.random.default_rng(e)
        meta = {"task": TASK, "seed": e, "obs_labels": task.obs_spec.labels(), "action_labels": list(ACTION_LABELS)}
        with EpisodeWriter(out / f"{TASK}_seed{e:06d}.mcap", meta, cameras=cams) as w:
            for t in range(steps):
                act = np.r_[rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0]), [0, 1, 0, 1, 0, 0], [-1.0]]
                images = {c["name"]: rng.integers(0, 256, (84, 84, 3), dtype=np.uint8) for c in cams}
                shown[(e, t)] = images
                w.write_step(
                    t, rng.normal(size=task.obs_spec.dim), act, act[:3], [0, 0, 0, 1.0], 0.04, False, images=images
                )
            w.finish(True, steps, "success")
    return out, shown


def test_frames_a_policy_saw_export_as_lerobot_image_features_and_import_back(tmp_path):
    folder, shown = _seeing_folder(tmp_path / "demos")
    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"]["observation.images.front"] == {
        "dtype": "image",
        "shape": [84, 84, 3],
        "names": ["height", "width", "channels"],
    }
    stats = json.loads((root / "meta" / "stats.json").read_text())["observation.images.wrist"]
    assert np.asarray(stats["mean"]).shape == (3, 1, 1) and 0.4 < np.asarray(stats["mean"]).mean() < 0.6
    ds = _load(root).cast_column("observation.images.front", datasets.Image())  # as LeRobot casts it
    row = ds[5]  # the second episode's second frame
    assert (row["episode_index"], row["frame_index"]) == (1, 1)
    np.testing.assert_array_equal(np.asarray(row["observation.images.front"]), shown[(1, 1)]["front"])
    task = make_task(TASK, images=True)
    cams = [c.to_json() for c in task.cameras]
    spec = task.obs_spec
    args = (root, tmp_path / "back", TASK, spec.labels(), list(ACTION_LABELS))
    report = import_dataset(*args, pose_from_state=spec.ee_pose, progress=False, cameras=cams)
    assert (report.episodes, report.frames) == (2, 10)
    back = read_episode(sorted((tmp_path / "back").glob("*.mcap"))[1])
    np.testing.assert_array_equal(back.frames("wrist")[3], shown[(1, 3)]["wrist"])


def test_a_foreign_image_dataset_that_does_not_fit_is_refused_naming_each_camera(tmp_path):
    folder, _ = _seeing_folder(tmp_path / "demos", episodes=(3,))
    root = tmp_path / "ds"
    write_dataset(from_folder(folder), root, FPS, list(ACTION_LABELS), progress=False)
    spec = make_task(TASK, images=True).obs_spec
    args = (root, tmp_path / "back", TASK, spec.labels(), list(ACTION_LABELS))

    def edit(info):
        info["features"]["observation.images.wrist"]["dtype"] = "video"
        info["features"]["observation.images.front"]["shape"] = [96, 96, 3]

    _edit_info(root, edit)
    cams = [
        {"name": "front", "size": 84, "crop": 76},
        {"name": "wrist", "size": 84, "crop": 76},
        {"name": "side", "size": 84, "crop": 76},
    ]
    with pytest.raises(LeRobotImportError) as err:
        import_dataset(*args, pose_from_state=spec.ee_pose, progress=False, cameras=cams)
    text = str(err.value)
    assert "observation.images.front: shape [96, 96, 3], the task renders 'front' at [84, 84, 3]" in text
    assert "observation.images.wrist: a video feature" in text
    assert "observation.images.side: missing (the policy sees 'side'" in text
    assert not (tmp_path / "back").exists()

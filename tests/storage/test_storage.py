import json
import shutil

import numpy as np
import pytest

from sim.demos import record_demos
from sim.tasks.lift import LIFT_OBS
from storage import keys
from storage.dataset import DatasetConfig, DatasetError, load_dataset
from storage.episodes import EpisodeReadError, EpisodeWriter, TruncatedEpisodeError, read_episode


def _synthetic_episode(path, steps=45, flush_every=10, finish=True, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(steps, 7))
    act = rng.normal(size=(steps, 10))
    ee = rng.normal(size=(steps, 3))
    quat = rng.normal(size=(steps, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    meta = {"task": "unit", "seed": seed, "expert": "test", "object": "none"}
    writer = EpisodeWriter(path, meta, object_names=["cube"], flush_every=flush_every, start_time_ns=10**18)
    for t in range(steps):
        writer.write_step(
            t, obs[t], act[t], ee[t], quat[t], 0.04, t == steps - 1, keys.SOURCE_EXPERT, {"cube": (ee[t] + 1, quat[t])}
        )
    if finish:
        writer.finish(True, steps, "success")
    else:
        writer.flush()
        crashed = path.read_bytes()  # what a crash leaves on disk: no summary, no footer
        writer.close()
        path.write_bytes(crashed)
    return obs, act, ee, quat


def test_mcap_round_trip_is_lossless(tmp_path):
    path = tmp_path / "ep.mcap"
    obs, act, ee, quat = _synthetic_episode(path)
    ep = read_episode(path)
    np.testing.assert_array_equal(ep.obs, obs)
    np.testing.assert_array_equal(ep.actions, act)
    np.testing.assert_array_equal(ep.ee_pose, np.concatenate([ee, quat], axis=1))
    assert ep.meta["task"] == "unit" and ep.meta["expert"] == "test"
    assert ep.outcome == {"success": True, "steps": 45, "reason": "success"}
    assert ep.success.tolist() == [False] * 44 + [True]
    assert ep.sources == [keys.SOURCE_EXPERT] * 45
    assert ep.playback_messages == 45 * 4  # tf ee + ee pose + tf cube + cube pose
    assert not ep.recovered


def test_playback_channels_use_foxglove_schemas(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "ep.mcap"
    _synthetic_episode(path, steps=3)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        tf = next(json.loads(m.data) for _, c, m in reader.iter_messages(topics=[keys.TOPIC_TF]))
    assert topics[keys.TOPIC_TF] == "foxglove.FrameTransform"
    assert topics[keys.TOPIC_EE_POSE] == "foxglove.PoseInFrame"
    assert topics[keys.TOPIC_OBJECT_POSE.format(name="cube")] == "foxglove.PoseInFrame"
    assert set(tf) == {"timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"}
    assert tf["parent_frame_id"] == keys.WORLD_FRAME


def test_truncated_file_recovers_every_flushed_message(tmp_path):
    path = tmp_path / "crashed.mcap"
    obs, act, _, _ = _synthetic_episode(path, steps=45, flush_every=10, finish=False)
    with pytest.raises(TruncatedEpisodeError, match="recover=True"):
        read_episode(path)
    ep = read_episode(path, recover=True)
    assert ep.recovered and ep.outcome is None
    assert len(ep) == 45  # the final flush covered every step
    np.testing.assert_array_equal(ep.actions, act)

    # cut the file mid-way, inside a chunk: every earlier flushed chunk survives, the cut one is lost
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    ep = read_episode(cut, recover=True)
    assert 10 <= len(ep) < 45 and len(ep) % 10 == 0  # whole flushes of 10 steps
    np.testing.assert_array_equal(ep.obs, obs[: len(ep)])


def test_corrupt_file_is_reported_by_name(tmp_path):
    path = tmp_path / "garbage.mcap"
    path.write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(EpisodeReadError, match="garbage.mcap"):
        read_episode(path, recover=True)


def _dataset_folder(tmp_path, lengths):
    folder = tmp_path / "demos"
    for i, n in enumerate(lengths):
        _synthetic_episode(folder / f"ep{i:02d}.mcap", steps=n, seed=i)
    return folder


def test_loader_history_and_chunk_indexing_at_episode_edges(tmp_path):
    folder = _dataset_folder(tmp_path, [4, 3])
    ds = load_dataset(folder, DatasetConfig(obs_horizon=2, action_horizon=3, val_fraction=0.0))
    assert ds.episode_ends.tolist() == [4, 7]
    obs, act = ds.windows(ds.sample_index(np.array([0, 1])))
    assert obs.shape == (7, 2, 7) and act.shape == (7, 3, 10)
    o, a = ds.obs, ds.actions
    # first step of each episode: the history is padded with its own first observation
    np.testing.assert_array_equal(obs[0], o[[0, 0]])
    np.testing.assert_array_equal(obs[4], o[[4, 4]])
    np.testing.assert_array_equal(obs[5], o[[4, 5]])
    # never reaches across episodes; chunks are padded with the episode's last action
    np.testing.assert_array_equal(act[2], a[[2, 3, 3]])
    np.testing.assert_array_equal(act[3], a[[3, 3, 3]])
    np.testing.assert_array_equal(act[4], a[[4, 5, 6]])
    np.testing.assert_array_equal(act[6], a[[6, 6, 6]])


def test_loader_split_is_by_episode_and_cache_is_used(tmp_path):
    folder = _dataset_folder(tmp_path, [5, 6, 7, 8, 9])
    config = DatasetConfig(val_fraction=0.2, split_seed=3)
    ds = load_dataset(folder, config)
    assert not ds.from_cache
    train, val = ds.split()
    assert len(val) == 1 and len(train) == 4 and not set(train) & set(val)
    assert len(ds.arrays("train")[keys.OBS]) + len(ds.arrays("val")[keys.OBS]) == 35
    again = load_dataset(folder, config)
    assert again.from_cache
    np.testing.assert_array_equal(again.obs, ds.obs)
    assert again.names == ds.names
    # a changed folder invalidates the cache
    _synthetic_episode(folder / "ep99.mcap", steps=4, seed=9)
    assert not load_dataset(folder, config).from_cache


def test_loader_reports_bad_files_by_name(tmp_path):
    folder = _dataset_folder(tmp_path, [5, 6])
    (folder / "broken.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 50)
    _synthetic_episode(folder / "crashed.mcap", steps=25, flush_every=10, finish=False)
    with pytest.raises(DatasetError) as err:
        load_dataset(folder)
    assert set(err.value.problems) == {"broken.mcap", "crashed.mcap"}
    assert "crashed.mcap" in str(err.value) and "recover=True" in str(err.value)
    (folder / "broken.mcap").unlink()
    ds = load_dataset(folder, DatasetConfig(recover=True))
    assert "crashed.mcap" in ds.names and ds.num_episodes == 3


def test_dataset_config_validation():
    with pytest.raises(ValueError, match="obs_horizon"):
        DatasetConfig(obs_horizon=0)
    with pytest.raises(ValueError, match="val_fraction"):
        DatasetConfig(val_fraction=1.5)


def test_recorded_demos_are_readable_training_data(tmp_path):
    out = tmp_path / "lift"
    paths, successes = record_demos("lift-cube", 2, out, seed=0, progress=False)
    assert successes == 2
    assert [p.name for p in paths] == ["lift-cube_seed000000.mcap", "lift-cube_seed000001.mcap"]
    ep = read_episode(paths[0])
    assert ep.meta["task"] == "lift-cube" and ep.meta["seed"] == 0 and ep.meta["object"] == "cube"
    assert ep.meta["expert"] == "lift-scripted"
    assert ep.outcome["success"] and ep.success[-1]
    assert ep.obs.shape[1] == LIFT_OBS.dim and ep.actions.shape[1] == 10
    # the recorded end-effector position is the observation's eef_pos
    np.testing.assert_allclose(ep.ee_pose[:, :3], ep.obs[:, :3])
    ds = load_dataset(out, DatasetConfig(obs_horizon=2, action_horizon=8, val_fraction=0.5))
    train = ds.arrays("train")
    assert train[keys.OBS].shape[1:] == (2, LIFT_OBS.dim) and train[keys.ACTION].shape[1:] == (8, 10)
    shutil.rmtree(out)


def test_field_arrows_point_along_the_vectors():
    from scipy.spatial.transform import Rotation

    from storage.segments import field_scene_update

    vectors = np.array([[1.0, 0, 0], [0, 2.0, 0], [-1.0, 0, 0], [0.3, -0.4, 0.5], [0, 0, 0]])
    update = field_scene_update(0, np.zeros((5, 3)), vectors, np.array([0, 1, 0, 1, 0]), scale=0.01)
    arrows = update["entities"][0]["arrows"]
    assert len(arrows) == 4  # the zero vector has no direction
    for arrow, v in zip(arrows, vectors[:4], strict=True):
        q = arrow["pose"]["orientation"]
        x_axis = Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).apply([1.0, 0, 0])
        np.testing.assert_allclose(x_axis, v / np.linalg.norm(v), atol=1e-9)
        assert arrow["shaft_length"] + arrow["head_length"] == pytest.approx(np.linalg.norm(v) * 0.01)


@pytest.mark.parametrize(("flush_seconds", "fsync"), [(0.0, False), (0.0, True), (3600.0, False)])
def test_a_step_is_on_disk_when_write_step_returns_only_with_a_flush_per_step(tmp_path, flush_seconds, fsync):
    """What a crash of the writer right after a step keeps: read while the writer is still open, as
    recovery reads a file whose writer was killed."""
    from storage.segments import SegmentWriter, read_segment

    path = tmp_path / "takeover.mcap"
    writer = SegmentWriter(path, {"robot": 0}, flush_seconds=flush_seconds, fsync=fsync)
    act = np.r_[[0.0, 0.0, 0.9], [0, 1, 0, 1, 0, 0], [-1.0]]
    kept = []
    for t in range(5):  # small steps: no chunk fills up on its own
        writer.write_step(np.full(26, t, np.float32), {"t": t}, act, act, act[:3], [0, 0, 0, 1.0], 0.1)
        kept.append(len(read_segment(path, recover=True).steps))
    writer.close("closed", "hand-back")
    assert kept == ([1, 2, 3, 4, 5] if flush_seconds == 0 else [0, 0, 0, 0, 0])

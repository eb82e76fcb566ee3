"""The frames a policy saw, in MCAP episodes and the dataset that trains on them."""

import base64
import json

import numpy as np
import pytest
from mcap.reader import make_reader

from storage import keys
from storage.dataset import DatasetError, load_dataset
from storage.episodes import EpisodeReadError, EpisodeWriter, read_episode

CAMS = [{"name": "front", "size": 8, "crop": 6}, {"name": "wrist", "size": 8, "crop": 6}]


def _frames(t, seed=0):
    rng = np.random.default_rng([seed, t])
    return {c["name"]: rng.integers(0, 256, (8, 8, 3), dtype=np.uint8) for c in CAMS}


def _write(path, steps=5, seed=0, cameras=CAMS, frames=_frames):
    with EpisodeWriter(path, {"task": "unit", "seed": seed}, cameras=cameras) as w:
        for t in range(steps):
            obs = np.full(4, t + seed, float)
            w.write_step(t, obs, np.zeros(10), np.zeros(3), [0, 0, 0, 1], 0.04, t == steps - 1, images=frames(t, seed))
        w.finish(True, steps)


def test_frames_round_trip_losslessly_as_foxglove_png(tmp_path):
    path = tmp_path / "ep.mcap"
    _write(path)
    ep = read_episode(path)
    assert ep.cameras == CAMS
    for name in ("front", "wrist"):
        np.testing.assert_array_equal(ep.frames(name), np.stack([_frames(t)[name] for t in range(5)]))
    with open(path, "rb") as f:  # any MCAP reader sees Foxglove's CompressedImage, PNG, at the step's time
        reader = make_reader(f)
        schemas = {s.name for s in reader.get_summary().schemas.values()}
        got = [(c.topic, json.loads(m.data)) for _, c, m in reader.iter_messages(topics=["/observation/images/front"])]
    assert keys.SCHEMA_COMPRESSED_IMAGE in schemas and len(got) == 5
    assert all(m["format"] == "png" and base64.b64decode(m["data"])[:4] == b"\x89PNG" for _, m in got)


def test_the_writer_refuses_missing_or_misshapen_frames(tmp_path):
    with EpisodeWriter(tmp_path / "ep.mcap", {"task": "unit"}, cameras=CAMS) as w:
        args = (0, np.zeros(4), np.zeros(10), np.zeros(3), [0, 0, 0, 1], 0.04, False)
        with pytest.raises(ValueError, match="declared"):
            w.write_step(*args, images={"front": _frames(0)["front"]})
        with pytest.raises(ValueError, match="uint8"):
            w.write_step(*args, images={"front": np.zeros((8, 8, 3)), "wrist": _frames(0)["wrist"]})
        with pytest.raises(ValueError, match="declared 8x8"):
            w.write_step(*args, images={"front": np.zeros((9, 8, 3), np.uint8), "wrist": _frames(0)["wrist"]})


def test_the_dataset_decodes_frames_once_and_maps_them_afterwards(tmp_path):
    for s in range(3):
        _write(tmp_path / f"unit_seed{s:06d}.mcap", steps=4 + s, seed=s)
    ds = load_dataset(tmp_path)
    assert not ds.from_cache and ds.cameras == CAMS and ds.images["front"].shape == (4 + 5 + 6, 8, 8, 3)
    again = load_dataset(tmp_path)
    assert again.from_cache and isinstance(again.images["wrist"], np.memmap)
    np.testing.assert_array_equal(np.asarray(again.images["wrist"]), ds.images["wrist"])
    arrays = again.arrays("all")
    front = arrays[keys.image_key("front")]
    assert front.shape == (15, 1, 8, 8, 3) and front.dtype == np.uint8
    np.testing.assert_array_equal(front[4, 0], _frames(0, seed=1)["front"])  # the second episode's first step


def test_a_corrupt_frame_or_mixed_cameras_is_named(tmp_path):
    _write(tmp_path / "a.mcap")

    def broken(t, seed):
        return _frames(t, seed) | ({"wrist": np.zeros((8, 8, 3), np.uint8)} if t else {})

    _write(tmp_path / "b.mcap", cameras=CAMS[:1], frames=lambda t, s: {"front": _frames(t, s)["front"]})
    with pytest.raises(DatasetError, match="b.mcap: recorded cameras"):
        load_dataset(tmp_path, None)
    (tmp_path / "b.mcap").unlink()
    path = tmp_path / "c.mcap"
    _write(path, frames=broken)
    ep = read_episode(path)
    ep.images["wrist"][2] = dict(ep.images["wrist"][2], data=base64.b64encode(b"not a png").decode())
    with pytest.raises(EpisodeReadError, match="camera 'wrist': not a PNG"):
        ep.frames("wrist")
    with pytest.raises(EpisodeReadError, match="no camera 'side'"):
        ep.frames("side")

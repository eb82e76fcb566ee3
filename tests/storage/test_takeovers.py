"""Which takeovers and steps fine-tuning learns from (``TakeoverSelection``), read from real segment files."""

import numpy as np
import pytest

from policy.finetune import FinetuneConfig
from storage import keys
from storage.mcap_io import JsonMcapWriter
from storage.segments import SCHEMAS, SegmentStep, SegmentWriter, read_segment, recover_segment
from storage.takeovers import TakeoverSelection, load_takeovers


def _segment(path, steps: int, first: int = 0):
    """A closed segment whose observations are its step numbers from ``first``."""
    w = SegmentWriter(path, {"robot": 0})
    for t in range(first, first + steps):
        act = np.r_[[0.0, 0.0, 0.9], [0, 1, 0, 1, 0, 0], [-1.0]]
        w.write_step(np.full(26, t, np.float32), {}, act, act * 0, act[:3], [0, 0, 0, 1.0], None)
    w.close("closed", "hand-back")
    return path


def test_the_reader_keeps_the_last_steps_of_each_takeover(tmp_path):
    paths = [_segment(tmp_path / "a.mcap", 5), _segment(tmp_path / "b.mcap", 2, first=200)]
    assert len(load_takeovers(paths, obs_dim=26)) == 7
    out = load_takeovers(paths, obs_dim=26, selection=TakeoverSelection(tail=3))
    # the last 3 steps of the 5-step takeover (the ones that led to its end), all of the 2-step one
    assert out.obs[:, 0].tolist() == [2, 3, 4, 200, 201] and out.episode_ends.tolist() == [3, 5]
    assert out.used == ["a.mcap", "b.mcap"]


def test_successful_only_keeps_takeovers_of_episodes_that_succeeded():
    keep = TakeoverSelection(successful_only=True)
    assert keep.why_excluded("success") is None
    assert keep.why_excluded("timeout") == "its episode ended in timeout (successful episodes only)"
    assert "has not ended" in keep.why_excluded(None)
    assert TakeoverSelection().why_excluded("faulted") is None  # by default every takeover is used
    assert TakeoverSelection(tail=4).steps(10) == slice(6, 10) and TakeoverSelection(tail=4).steps(3) == slice(0, 3)


def test_a_segment_reads_as_typed_steps_and_a_malformed_step_is_named(tmp_path):
    segment = read_segment(_segment(tmp_path / "a.mcap", 2))
    assert segment.request is None  # written without the request it answered (before it was recorded): none
    step = segment.steps[1]
    assert isinstance(step, SegmentStep) and step.t == 1 and step.observation == [1.0] * 26
    assert step.position == [0.0, 0.0, 0.9] and step.quaternion == [0, 0, 0, 1.0] and step.command == {}
    assert step.uncertainty is None and step.shadow == {} and len(step.action) == len(step.action_normalized) == 10
    # a step without a position: the fine-tuning reader names it; recovery still counts it
    mcap = JsonMcapWriter(tmp_path / "bad.mcap", SCHEMAS, chunk_size=1024)
    for topic, schema, doc in (
        (keys.TOPIC_TAKEOVER, keys.SCHEMA_TAKEOVER, {"robot": 0}),
        (keys.TOPIC_TAKEOVER_STEP, keys.SCHEMA_TAKEOVER_STEP, {"observation": [0.0] * 26, "action": [0.0] * 10}),
        (keys.TOPIC_TAKEOVER_END, keys.SCHEMA_TAKEOVER_END, {"status": "closed", "ended_by": None, "steps": 1}),
    ):
        mcap.add(mcap.channel(topic, schema), 1, doc)
    mcap.close()
    out = load_takeovers([tmp_path / "bad.mcap"], obs_dim=26)
    assert out.skipped == {"bad.mcap": "malformed step (KeyError: 'position')"}
    assert recover_segment(tmp_path / "bad.mcap") == 1


@pytest.mark.parametrize("tail", [0, -2, 2.5, True, "3"])
def test_a_bad_tail_is_refused_with_its_value(tail):
    with pytest.raises(ValueError, match="takeover tail must be an integer >= 1"):
        TakeoverSelection(tail=tail)
    with pytest.raises(ValueError, match="takeover tail must be an integer >= 1"):
        FinetuneConfig(takeover_tail=tail)


def test_a_segment_recorded_with_another_observation_layout_is_left_out_naming_its_channels(tmp_path):
    from sim.registry import make_task
    from tests.helpers import write_segment

    lift, cup = make_task("lift-cube").obs_spec, make_task("cup-stack").obs_spec
    swapped = lift.labels()[:11] + lift.labels()[20:23] + lift.labels()[11:20] + lift.labels()[23:]
    paths = [
        write_segment(tmp_path / "same.mcap", lift.dim, seed=1, obs_labels=lift.labels()),
        write_segment(tmp_path / "old.mcap", lift.dim, seed=2),  # written before segments named their channels
        write_segment(tmp_path / "swapped.mcap", lift.dim, seed=3, obs_labels=swapped),  # the same size
        write_segment(tmp_path / "cup.mcap", cup.dim, seed=4, task="cup-stack", obs_labels=cup.labels()),
    ]
    out = load_takeovers(paths, obs_dim=lift.dim, obs_labels=lift.labels())
    assert out.used == ["same.mcap", "old.mcap"] and len(out) == 10
    assert out.skipped["swapped.mcap"] == (
        "recorded with another observation layout than the policy's (task lift-nut, observations [eef_pos(3), "
        "eef_rot6d(6), gripper_qpos(2), object_to_eef_pos(3), object_pos(3), object_rot6d(6), object_extent(3), "
        "finger_rays(6)]): the same channels in another order (at channel 11: object_to_eef_pos, not object_pos)"
    )
    assert out.skipped["cup.mcap"].startswith(
        "recorded with another observation layout than the policy's (task cup-stack"
    )
    assert (
        "missing object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays; extra green_pos"
        in out.skipped["cup.mcap"]
    )
    # without the policy's layout (an older checkpoint), segments are judged by their size alone
    old_policy = load_takeovers(paths, obs_dim=lift.dim)
    assert old_policy.used == ["same.mcap", "old.mcap", "swapped.mcap"]
    assert f"the policy takes {lift.dim} per step" in old_policy.skipped["cup.mcap"]


def test_takeovers_of_a_policy_that_sees_carry_the_frames_it_saw(tmp_path):
    from tests.helpers import write_segment

    cams = [{"name": "front", "size": 8, "crop": 6}]
    rng = np.random.default_rng(0)
    paths, shown = [], []
    for i, steps in enumerate((3, 4)):
        w = SegmentWriter(tmp_path / f"s{i}.mcap", {"robot": 0, "task": "lift-cube", keys.CAMERAS: cams})
        for _ in range(steps):
            frame = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
            shown.append(frame)
            act = np.r_[0.0, 0.0, 0.9, 1, 0, 0, 0, 1, 0, 1.0]
            w.write_step(np.zeros(11), {}, act, act, act[:3], [0, 0, 0, 1.0], 0.1, images={"front": frame})
        with pytest.raises(ValueError, match="declared"):
            w.write_step(np.zeros(11), {}, act, act, act[:3], [0, 0, 0, 1.0], 0.1)
        w.close("closed", "hand-back")
        paths.append(tmp_path / f"s{i}.mcap")
    plain = write_segment(tmp_path / "plain.mcap", 11)  # recorded for a state-only policy: no frames
    out = load_takeovers([*paths, plain], obs_dim=11, cameras=["front"])
    assert out.used == ["s0.mcap", "s1.mcap"] and "no frames of camera 'front'" in out.skipped["plain.mcap"]
    np.testing.assert_array_equal(out.images["front"], np.stack(shown))
    arrays = out.arrays(1, 1)
    assert arrays[keys.image_key("front")].shape == (7, 1, 8, 8, 3)
    np.testing.assert_array_equal(read_segment(paths[1]).frames("front"), np.stack(shown[3:]))

"""What tells two observation layouts apart, by channel name, on the registered tasks' real layouts."""

from __future__ import annotations

from sim.registry import make_task
from storage.obs_layout import describe, difference, mismatched, parts, recorded

CUP = make_task("cup-stack").obs_spec
LIFT = make_task("lift-cube").obs_spec


def test_labels_group_back_into_the_specs_parts():
    for task in ("lift-cube", "cup-stack", "open-drawer"):
        spec = make_task(task).obs_spec
        assert parts(spec.labels()) == list(spec.parts)
    assert describe(CUP.labels()).endswith("red_observed_to_green_pos(3), red_visible]")
    assert describe(["joint_pos[0]", "a"]) == "[joint_pos[0], a]"  # one dimension of a part: as labelled


def test_missing_extra_and_reordered_channels_are_named():
    cup = CUP.labels()
    assert difference(cup, cup) == []
    without = [label for label in cup if label != "red_visible"] + ["red_rim_z"]
    assert difference(cup, without) == ["missing red_visible", "extra red_rim_z"]
    # a whole part is named as the part, one dimension of it as that dimension
    assert difference(cup, [label for label in cup if label != "green_pos[1]"]) == ["missing green_pos[1]"]
    assert difference(cup, LIFT.labels()) == [
        "missing green_pos, green_rot6d, red_pos_observed, green_to_eef_pos, red_observed_to_green_pos, red_visible",
        "extra object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays",
    ]
    swapped = cup[:3] + cup[9:11] + cup[3:9] + cup[11:]  # gripper before the rotation: the same size
    assert difference(cup, swapped) == [
        "the same channels in another order (at channel 3: gripper_qpos, not eef_rot6d)"
    ]
    inner = cup[:3] + [cup[4], cup[3]] + cup[5:]
    assert difference(cup, inner) == [
        "the same channels in another order (at channel 3: eef_rot6d[1], not eef_rot6d[0])"
    ]
    assert difference(cup, cup + ["red_visible"]) == ["31 channels, not 30"]


def test_files_are_judged_only_on_a_layout_they_record():
    lift = LIFT.labels()
    files = [
        ("same.mcap", {"obs_labels": lift}),
        ("old.mcap", {"task": "lift-cube"}),
        ("cup.mcap", {"obs_labels": CUP.labels()}),
    ]
    out = mismatched(files, lift)
    assert list(out) == ["cup.mcap"]
    assert out["cup.mcap"].startswith("recorded with another observation layout ([eef_pos(3), eef_rot6d(6)")
    assert "missing object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays" in out["cup.mcap"]
    assert recorded({"obs_labels": "eef_pos"}) is None and recorded(None) is None and recorded({}) is None

"""``check_fits``: a checkpoint that cannot run a task is refused, naming what differs; the bundled
policies record the layout they were trained on and fit their tasks."""

from __future__ import annotations

from pathlib import Path

import pytest

from policy.checkpoint import CheckpointError, check_fits, layout_info, read_info, save_policy
from policy.config import DiffusionPolicyConfig
from sim.env import ROBOT_OBS
from sim.registry import make_task
from tests.helpers import tiny_policy

ROOT = Path(__file__).resolve().parents[2]
CUP = make_task("cup-stack").obs_spec.labels()
LIFT_DIM = make_task("lift-cube").obs_spec.dim


def _info(task: str, **config) -> dict:
    """A config.json as ``hitl train`` writes it for ``task`` (its layout recorded), with ``config``."""
    spec = make_task(task).obs_spec
    cfg = DiffusionPolicyConfig(**{"obs_dim": spec.dim, "network": "mlp", **config})
    return {"policy": cfg.to_dict(), "task": task, **layout_info(spec)}


SERVES = {
    "lift-cube": ["lift-cube", "lift-nut", "lift-hammer", "lift-hook"],
    "cup-stack": ["cup-stack"],
    "open-drawer": ["open-drawer"],
}


def test_the_bundled_policies_see_their_tasks_cameras_and_fit_what_they_serve():
    for name, tasks in SERVES.items():
        info = read_info(ROOT / "policies" / name)
        task = make_task(name, images=True)
        assert info["obs_labels"] == task.obs_spec.labels() == ROBOT_OBS.labels()  # the robot's own state only
        assert [c["name"] for c in info["policy"]["cameras"]] == [c.name for c in task.cameras]
        for served in tasks:
            check_fits(info, served, name)
    with pytest.raises(CheckpointError) as err:
        check_fits(read_info(ROOT / "policies" / "cup-stack"), "lift-cube", "policies/cup-stack")
    assert str(err.value) == (
        "policy policies/cup-stack cannot run task lift-cube: it sees camera 'side', which task lift-cube lacks "
        "(it has front, wrist); it sees 'wrist' at 104 pixels, task lift-cube renders 84; "
        "it sees 'front' at 104 pixels, task lift-cube renders 84"
    )


def test_the_state_based_policies_fit_their_tasks_state_and_are_refused_elsewhere_by_channel_name():
    for name, tasks in SERVES.items():
        info = read_info(ROOT / "policies" / "state" / name)
        assert info["obs_labels"] == make_task(name).obs_spec.labels()
        for task in tasks:
            check_fits(info, task, name)
    with pytest.raises(CheckpointError) as err:
        check_fits(read_info(ROOT / "policies" / "state" / "cup-stack"), "lift-cube", "policies/state/cup-stack")
    message = str(err.value)
    assert message.startswith(
        "policy policies/state/cup-stack cannot run task lift-cube: it was trained on observations [eef_pos(3)"
    )
    assert "task lift-cube gives [eef_pos(3), eef_rot6d(6), gripper_qpos(2), object_pos(3)" in message
    assert (
        "missing green_pos, green_rot6d, red_pos_observed, green_to_eef_pos, red_observed_to_green_pos, red_visible"
        in message
    )
    assert "extra object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays" in message


def test_a_layout_of_the_same_size_that_differs_is_refused_by_channel_name():
    # a policy trained when cup-stack observed the red cup's rim instead of whether it was visible
    info = _info("cup-stack") | {"obs_labels": [label for label in CUP if label != "red_visible"] + ["red_rim_z"]}
    with pytest.raises(CheckpointError, match=r"cannot run task cup-stack: .*: missing red_rim_z; extra red_visible$"):
        check_fits(info, "cup-stack")
    swapped = CUP[:3] + CUP[9:11] + CUP[3:9] + CUP[11:]
    with pytest.raises(CheckpointError, match=r"in another order \(at channel 3: eef_rot6d, not gripper_qpos\)"):
        check_fits(_info("cup-stack") | {"obs_labels": swapped}, "cup-stack")
    with pytest.raises(CheckpointError, match="records 29 observation channels for 30-dim inputs"):
        check_fits(_info("cup-stack") | {"obs_labels": CUP[:-1]}, "cup-stack")


def test_a_checkpoint_without_a_layout_is_judged_by_its_observation_size(tmp_path):
    save_policy(tiny_policy("lift-cube"), tmp_path / "old", {"task": "lift-cube"})  # as before layouts were recorded
    old = read_info(tmp_path / "old")
    assert "obs_labels" not in old
    check_fits(old, "lift-hammer", "old")  # the same size: served as before
    with pytest.raises(CheckpointError) as err:
        check_fits(old, "open-drawer", "old")
    assert str(err.value) == (
        f"policy old cannot run task open-drawer: it takes {LIFT_DIM}-dim observations (its config.json records no "
        "layout), task open-drawer gives 23: [eef_pos(3), eef_rot6d(6), gripper_qpos(2), drawer_opening(3), "
        "handle_pos(9)]"
    )


def test_action_size_and_chunking_that_cannot_run_the_task_are_refused():
    with pytest.raises(CheckpointError, match="it predicts 7-dim actions, the tasks take 10"):
        check_fits(_info("lift-cube", action_dim=7), "lift-cube")
    check_fits(_info("lift-cube", action_horizon=150, obs_horizon=150), "lift-cube")  # the whole horizon: fits
    with pytest.raises(CheckpointError) as err:
        check_fits(_info("lift-cube", action_horizon=151, obs_horizon=200), "lift-nut", "chunky")
    assert str(err.value) == (
        "policy chunky cannot run task lift-nut: its action_horizon of 151 steps is longer than task lift-nut's "
        "horizon of 150; its obs_horizon of 200 steps is longer than task lift-nut's horizon of 150"
    )
    check_fits(_info("cup-stack", action_horizon=200), "cup-stack")  # cup-stack's horizon is 400
    with pytest.raises(CheckpointError, match="bad policy config"):
        check_fits({"task": "lift-cube"}, "lift-cube")
    with pytest.raises(KeyError, match="unknown task"):
        check_fits(_info("lift-cube"), "lift-everything")


def test_a_policy_whose_cameras_a_task_lacks_is_refused():
    from sim.env import ROBOT_OBS
    from sim.vision import CameraSpec

    def seeing(*cams):
        cfg = DiffusionPolicyConfig(obs_dim=ROBOT_OBS.dim, cameras=cams)
        return {"policy": cfg.to_dict(), "obs_labels": ROBOT_OBS.labels()}

    check_fits(seeing(CameraSpec("front", 84, 76), CameraSpec("wrist", 84, 76)), "lift-hammer")
    with pytest.raises(CheckpointError) as err:
        check_fits(seeing(CameraSpec("front", 84, 76), CameraSpec("wrist", 84, 76)), "open-drawer", "eyes")
    assert str(err.value) == (
        "policy eyes cannot run task open-drawer: it sees camera 'front', which task open-drawer lacks (it has "
        "side); it sees camera 'wrist', which task open-drawer lacks (it has side)"
    )
    with pytest.raises(CheckpointError, match="it sees 'side' at 84 pixels, task cup-stack renders 104"):
        check_fits(seeing(CameraSpec("side", 84, 76)), "cup-stack")
    state_based = {"obs_labels": make_task("lift-cube").obs_spec.labels()}  # not what a policy that sees observes
    with pytest.raises(CheckpointError, match="records 32 observation channels for 11-dim inputs"):
        check_fits(seeing(CameraSpec("front", 84, 76)) | state_based, "lift-cube")

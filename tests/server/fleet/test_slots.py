import json
import logging

from server.fleet.slots import load_slot
from server.settings import RobotGroup, Settings
from tests.helpers import tiny_policy_folder


def _settings(tmp_path, policy):
    return Settings(
        data_dir=tmp_path / "var",
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        inference={"trace_policies": False},
    )


def _calibration(policy, **check):
    path = policy / "calibration.json"
    record = json.loads(path.read_text())
    record["rollout_check"] = {"task": "lift-cube", "share_above": 0.4, "flag_share": 0.15, **check}
    path.write_text(json.dumps(record))


def test_a_policy_flagged_by_calibrate_is_served_with_a_warning(tmp_path, caplog):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    _calibration(policy, flagged=True)
    with caplog.at_level(logging.WARNING, logger="hitl.server"):
        slot = load_slot(_settings(tmp_path, policy), policy, "lift-cube", 1)
    assert slot.threshold == 0.5
    assert any("calibration problem: 40% of the steps" in r.getMessage() for r in caplog.records)


def test_a_policy_that_passed_its_check_loads_quietly(tmp_path, caplog):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    _calibration(policy, flagged=False)
    with caplog.at_level(logging.WARNING, logger="hitl.server"):
        load_slot(_settings(tmp_path, policy), policy, "lift-cube", 1)
    assert not [r for r in caplog.records if "calibration problem" in r.getMessage()]


def test_a_device_this_machine_lacks_is_refused_with_its_name(tmp_path):
    import pytest

    from server.errors import ServiceError

    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    settings = _settings(tmp_path, policy)
    settings = settings.model_copy(
        update={"inference": settings.inference.model_copy(update={"device": "cuda:99"})}
    )  # no machine has that one
    with pytest.raises(ServiceError, match="'cuda:99'") as err:
        load_slot(settings, policy, "lift-cube", 1)
    assert err.value.status == 422


def test_the_device_setting_is_validated():
    import pytest
    from pydantic import ValidationError

    for bad in ("gpu", "cuda:x", "mps"):
        with pytest.raises(ValidationError, match="device"):
            Settings(inference={"device": bad})
    assert Settings(inference={"device": "cuda:1"}).inference.device == "cuda:1"


def test_a_policy_trained_on_another_observation_layout_is_refused_naming_the_channels(tmp_path):
    import pytest

    from server.errors import ServiceError
    from sim.registry import make_task

    lift = make_task("lift-cube").obs_spec.labels()
    # the same size as lift-cube's observation, but the object's extent (and the finger rays after it) where its
    # position was
    moved = lift[:11] + lift[23:] + lift[11:23]
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5, obs_labels=moved)
    with pytest.raises(ServiceError) as err:
        load_slot(_settings(tmp_path, policy), policy, "lift-cube", 1)
    assert err.value.status == 422
    assert err.value.message == (
        f"policy {policy} cannot run task lift-cube: it was trained on observations [eef_pos(3), eef_rot6d(6), "
        "gripper_qpos(2), object_extent(3), finger_rays(6), object_pos(3), object_rot6d(6), object_to_eef_pos(3)], "
        "task lift-cube gives [eef_pos(3), eef_rot6d(6), gripper_qpos(2), object_pos(3), object_rot6d(6), "
        "object_to_eef_pos(3), object_extent(3), finger_rays(6)]: the same channels in another order (at channel 11: "
        "object_pos, not object_extent)"
    )
    # one that records the task's layout, or none (older checkpoints: by size), is served
    fits = tiny_policy_folder(tmp_path / "fits", "lift-cube", 0.5, obs_labels=lift)
    assert load_slot(_settings(tmp_path, fits), fits, "lift-nut", 1).task == "lift-nut"
    old = tiny_policy_folder(tmp_path / "old", "lift-cube", 0.5)
    with pytest.raises(
        ServiceError, match=f"{len(lift)}-dim observations .* no layout.*task cup-stack gives 30"
    ) as err:
        load_slot(_settings(tmp_path, old), old, "cup-stack", 1)
    assert err.value.status == 422

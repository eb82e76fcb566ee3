import json
import logging

from server.fleet.slots import load_slot
from server.settings import RobotGroup, Settings
from tests.helpers import tiny_policy_folder


def _settings(tmp_path, policy):
    return Settings(
        data_dir=tmp_path / "var",
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        trace_policies=False,
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
    settings = _settings(tmp_path, policy).model_copy(update={"device": "cuda:99"})  # no machine has that one
    with pytest.raises(ServiceError, match="'cuda:99'") as err:
        load_slot(settings, policy, "lift-cube", 1)
    assert err.value.status == 422


def test_the_device_setting_is_validated():
    import pytest
    from pydantic import ValidationError

    for bad in ("gpu", "cuda:x", "mps"):
        with pytest.raises(ValidationError, match="device"):
            Settings(device=bad)
    assert Settings(device="cuda:1").device == "cuda:1"

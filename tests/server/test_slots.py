import json
import logging

from server.settings import RobotGroup, Settings
from server.slots import load_slot
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

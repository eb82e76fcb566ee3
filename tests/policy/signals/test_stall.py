import numpy as np
import pytest
import torch

from policy.hitl_state import RobotControl
from policy.signals import SignalInput, TriggerState, make_signal
from policy.signals.base import CalibrationData, SignalError, StepSet
from policy.signals.stall import StallConfig, gripper_open, policy_motion
from tests.helpers import tiny_policy

OPEN, CLOSED = -1.0, 1.0


def _action(pos, gripper=OPEN):
    """(10,) raw action at ``pos`` pointing down, gripper command ``gripper``."""
    return np.r_[pos, [0, 1, 0, 1, 0, 0], gripper].astype(np.float32)


def _chunks(starts, steps, gripper=OPEN, length=2):
    """(B, length, 10): from each start, ``length`` actions moving ``steps[b]`` (3,) per action."""
    return torch.as_tensor(
        np.stack(
            [
                np.stack([_action(np.asarray(s) + (i + 1) * np.asarray(d), gripper) for i in range(length)])
                for s, d in zip(starts, steps, strict=True)
            ]
        )
    )


def test_motion_is_metres_per_executed_step_to_where_the_chunk_goes():
    current = torch.as_tensor(np.stack([_action([0, 0, 1]), _action([0.1, 0, 1])]))
    chunk = _chunks([[0, 0, 1], [0.1, 0, 1]], [[0.003, 0.004, 0], [0, 0, -0.01]])
    np.testing.assert_allclose(policy_motion(chunk, current, 1).numpy(), [0.005, 0.01], rtol=1e-6)
    # two executed steps reach twice as far: the same per-step motion
    np.testing.assert_allclose(policy_motion(chunk, current, 2).numpy(), [0.005, 0.01], rtol=1e-6)
    closing = _chunks([[0, 0, 1]], [[0, 0, 0]], gripper=CLOSED)
    held = torch.as_tensor(_action([0, 0, 1], CLOSED))[None]
    assert gripper_open(chunk, current).tolist() == [True, True]
    assert gripper_open(closing, current[:1]).tolist() == [False]  # the policy closes: a grasp holds still
    assert gripper_open(chunk[:1], held).tolist() == [False]  # closed now


def _signal(**calibration):
    signal = make_signal("stall", tiny_policy(), StallConfig(patience=3))
    signal.calibration = {"threshold": 0.5, "stride": 0.01, **calibration}
    return signal


def _step(signal, motion, gripper=OPEN, ids=(0,)):
    """Scores robots ``ids`` whose policy moves ``motion`` (m) this step."""
    b = len(ids)
    current = np.stack([_action([0, 0, 1], OPEN)] * b)
    chunk = _chunks([[0, 0, 1]] * b, [[motion, 0, 0]] * b, gripper=gripper, length=1)
    batch = SignalInput(torch.zeros(b, 1, 26), torch.as_tensor(current), np.asarray(ids), action=chunk)
    scores = signal.score(batch)
    return scores, signal.wants_help(scores, TriggerState(ids))


def test_stillness_is_the_missing_share_of_the_usual_stride():
    signal = _signal()
    for motion, want in [(0.0, 1.0), (0.002, 0.8), (0.01, 0.0), (0.03, 0.0)]:
        scores, _ = _step(signal, motion)
        assert scores.value[0] == pytest.approx(want, abs=1e-6)
        assert scores.parts["motion"][0] == pytest.approx(motion, abs=1e-7)
    scores, _ = _step(signal, 0.0, gripper=CLOSED)
    assert scores.value[0] == 0.0  # closing the gripper is not a stall


def test_asks_after_patience_still_steps_in_a_row_per_robot():
    signal = _signal()
    asks = [_step(signal, 0.001)[1][0] for _ in range(3)]
    assert asks == [False, False, True]
    assert not _step(signal, 0.02)[1][0]  # moving again: the count restarts
    assert [_step(signal, 0.001)[1][0] for _ in range(3)] == [False, False, True]
    _, wants = _step(signal, 0.001, ids=(0, 1))  # robot 1 only starts counting now
    assert wants.tolist() == [True, False]
    signal.reset([0])
    assert not _step(signal, 0.001)[1][0]


def _val(positions_per_episode, gripper):
    obs, current, episode, t = [], [], [], []
    for e, positions in enumerate(positions_per_episode):
        for i, p in enumerate(positions):
            obs.append(np.zeros((1, 26), np.float32))
            current.append(_action(p, gripper))
            episode.append(e)
            t.append(i)
    m = len(obs)
    return StepSet(
        np.stack(obs),
        np.stack(current)[:, None],
        np.stack(current),
        np.asarray(episode),
        np.asarray(t),
        np.full(m, 3),
        np.ones(m, bool),
        ["a", "b"],
    )


def test_calibration_takes_the_policys_median_open_gripper_stride(monkeypatch):
    signal = make_signal("stall", tiny_policy(), StallConfig(quantile=0.5, calibration_batch=3))
    motions = torch.tensor([0.0, 0.01, 0.02, 0.03, 0.005, 0.015], dtype=torch.float64)
    calls = []

    def sample_chunks(obs, k):  # the policy's next action: `motions[i]` along x from each step's pose
        rows = torch.arange(len(calls) * 3, len(calls) * 3 + len(obs))
        calls.append(len(obs))
        current = torch.as_tensor(np.stack([_action([0, 0, 1])] * len(obs)))
        chunk = current[:, None].clone()
        chunk[:, 0, 0] += motions[rows].float()
        return chunk[:, None]

    monkeypatch.setattr(signal, "sample_chunks", sample_chunks)
    data = CalibrationData(train=_val([[[0, 0, 1]] * 6], OPEN), val=_val([[[0, 0, 1]] * 6], OPEN))
    rec = signal.calibrate(data)
    assert calls == [3, 3]
    assert rec["stride"] == pytest.approx(0.0125, rel=1e-5)  # median of the six motions
    still = np.clip(1 - motions.numpy() / 0.0125, 0, 1)
    assert rec["threshold"] == pytest.approx(float(np.quantile(still, 0.5)), rel=1e-5)
    assert rec["samples"] == 6
    closed = make_signal("stall", tiny_policy())
    monkeypatch.setattr(closed, "sample_chunks", sample_chunks)
    calls.clear()
    with pytest.raises(SignalError, match="no open-gripper steps"):
        closed.calibrate(CalibrationData(train=_val([[[0, 0, 1]] * 3], CLOSED), val=_val([[[0, 0, 1]] * 3], CLOSED)))


def test_config_is_validated():
    with pytest.raises(ValueError, match="patience"):
        StallConfig(patience=0)
    with pytest.raises(ValueError, match="quantile"):
        StallConfig(quantile=1.0)


def _undo_signal(**config):
    signal = make_signal("stall", tiny_policy(), StallConfig(patience=1, reask_undo=True, **config))
    signal.calibration = {"threshold": 0.5, "stride": 0.01}
    return signal


_CONTROLS: dict[int, RobotControl] = {}  # robot 0's control state per signal: what the controller keeps


def _at(signal, pos, to, gripper_now=OPEN, gripper_plan=OPEN, teleop=False):
    """One step of robot 0 standing at ``pos`` whose policy plans to go to ``to`` (m); its takeover facts
    come from a control state, as the controller passes them."""
    control = _CONTROLS.setdefault(id(signal), RobotControl())
    current = torch.as_tensor(_action(pos, gripper_now))[None]
    chunk = torch.as_tensor(_action(to, gripper_plan))[None, None]
    batch = SignalInput(torch.zeros(1, 1, 26), current, np.asarray([0]), action=chunk)
    scores = signal.score(batch)
    state = TriggerState(np.asarray([0]), np.asarray([teleop]), after_takeover=np.asarray([control.driven]))
    wants = bool(signal.wants_help(scores, state)[0])
    if teleop:
        control.operator_step(True, None, None, None)
    else:
        control.policy_step(None)
    return wants


def test_after_a_takeover_a_plan_back_to_where_the_robot_asked_asks_again():
    signal = _undo_signal()
    stop = [0.0, 0.0, 1.0]
    assert _at(signal, stop, stop)  # stalled: asks
    _at(signal, [0.01, 0, 1], [0.0, 0, 1], teleop=True)  # the operator drives it 2.5 cm across
    _at(signal, [0.025, 0, 1], [0.02, 0, 1], teleop=True)
    assert _at(signal, [0.025, 0, 1], [0.015, 0, 1])  # the policy would head back: ask again at once
    _at(signal, [0.04, 0, 1], [0.03, 0, 1], teleop=True)
    # the reference stays the pose where it first asked: heading back towards it again asks again
    assert _at(signal, [0.04, 0, 1], [0.03, 0, 1])
    _at(signal, [0.05, 0, 1], [0.05, 0, 1], teleop=True)
    assert not _at(signal, [0.05, 0, 1], [0.05, 0, 1.02])  # lifting away from it runs
    assert not _at(signal, [0.05, 0, 1.02], [0.04, 0, 1.02])  # and later steps are only checked for a stall


def test_a_takeover_that_moved_the_robot_less_than_undo_min_or_closed_the_gripper():
    signal = _undo_signal(undo_min=0.01)
    assert _at(signal, [0, 0, 1], [0, 0, 1])
    _at(signal, [0.005, 0, 1], [0, 0, 1], teleop=True)
    assert not _at(signal, [0.005, 0, 1], [-0.005, 0, 1])  # moved 5 mm: not worth a request
    signal.reset([0])
    assert _at(signal, [0, 0, 1], [0, 0, 1])
    _at(signal, [0, 0, 0.98], [0, 0, 1], gripper_now=CLOSED, teleop=True)  # the operator closed it
    assert _at(signal, [0, 0, 0.98], [0, 0, 0.98], gripper_now=CLOSED, gripper_plan=OPEN)  # reopening undoes it
    _at(signal, [0, 0, 0.98], [0, 0, 1], gripper_now=CLOSED, teleop=True)
    assert not _at(signal, [0, 0, 0.98], [0, 0, 1.0], gripper_now=CLOSED, gripper_plan=CLOSED)  # lifts: runs


def _urgent(signal):
    return bool(signal.urgent(TriggerState(np.asarray([0]), np.asarray([False])))[0])


def test_only_a_request_that_keeps_the_operators_work_is_urgent():
    signal = _undo_signal()
    assert _at(signal, [0, 0, 1], [0, 0, 1]) and not _urgent(signal)  # a stall can wait out a cooldown
    _at(signal, [0.03, 0, 1], [0.0, 0, 1], teleop=True)
    assert _at(signal, [0.03, 0, 1], [0.015, 0, 1]) and _urgent(signal)  # heading back: cannot wait
    _at(signal, [0.03, 0, 0.98], [0.03, 0, 0.98], gripper_now=CLOSED, teleop=True)
    assert not _at(signal, [0.03, 0, 0.98], [0.03, 0, 0.99], gripper_now=CLOSED, gripper_plan=CLOSED)
    assert not _urgent(signal)
    assert _at(signal, [0.03, 0, 0.99], [0.03, 0, 1.0], gripper_now=CLOSED, gripper_plan=OPEN) and _urgent(signal)
    with pytest.raises(SignalError, match="same robots"):
        signal.urgent(TriggerState(np.asarray([5]), np.asarray([False])))


def test_while_the_operators_grasp_holds_no_later_policy_step_lets_go():
    signal = _undo_signal()
    assert _at(signal, [0, 0, 1], [0, 0, 1])
    _at(signal, [0, 0, 0.98], [0, 0, 1], gripper_now=CLOSED, teleop=True)  # the operator grasps
    for z in (0.99, 1.0, 1.01):  # the policy lifts, closed: it runs
        assert not _at(signal, [0, 0, z], [0, 0, z + 0.01], gripper_now=CLOSED, gripper_plan=CLOSED)
    assert _at(signal, [0, 0, 1.02], [0, 0, 1.03], gripper_now=CLOSED, gripper_plan=OPEN)  # a later step lets go
    # once the gripper is open again (the operator let go) the policy's own grasps are its own
    _at(signal, [0, 0, 1.02], [0, 0, 1.02], teleop=True)
    assert not _at(signal, [0, 0, 1.02], [0, 0, 1.03])
    assert not _at(signal, [0, 0, 1.03], [0, 0, 1.04], gripper_now=CLOSED, gripper_plan=OPEN)
    signal.reset([0])
    assert not _at(signal, [0, 0, 1.0], [0, 0, 1.0], gripper_now=CLOSED, gripper_plan=OPEN)


def test_with_closed_grace_a_closed_gripper_that_stands_still_counts_after_the_grace():
    signal = make_signal("stall", tiny_policy(), StallConfig(patience=1, closed_grace=2))
    signal.calibration = {"threshold": 0.5, "stride": 0.01}
    # closing and holding still: not a stall for the first 2 closed steps, then one
    assert [_at(signal, [0, 0, 1], [0, 0, 1], gripper_now=CLOSED, gripper_plan=CLOSED) for _ in range(3)] == [
        False,
        False,
        True,
    ]
    assert not _at(signal, [0, 0, 1], [0, 0, 1.02], gripper_now=CLOSED, gripper_plan=CLOSED)  # lifting: moving
    assert not _at(signal, [0, 0, 1], [0.02, 0, 1])  # open (moving): the count of closed steps restarts
    assert not _at(signal, [0, 0, 1], [0, 0, 1], gripper_now=CLOSED, gripper_plan=CLOSED)
    signal.reset([0])
    off = make_signal("stall", tiny_policy(), StallConfig(patience=1))  # off by default: closed is never stuck
    off.calibration = {"threshold": 0.5, "stride": 0.01}
    assert not any(_at(off, [0, 0, 1], [0, 0, 1], gripper_now=CLOSED, gripper_plan=CLOSED) for _ in range(40))


def test_without_reask_undo_a_plan_back_is_only_scored_for_a_stall():
    signal = make_signal("stall", tiny_policy(), StallConfig(patience=1))
    signal.calibration = {"threshold": 0.5, "stride": 0.01}
    assert _at(signal, [0, 0, 1], [0, 0, 1])
    _at(signal, [0.03, 0, 1], [0.03, 0, 1], teleop=True)
    assert not _at(signal, [0.03, 0, 1], [0.015, 0, 1])


@pytest.mark.parametrize(
    "bad",
    [
        {"reask_undo": "yes"},
        {"undo_min": 0},
        {"undo_min": -0.01},
        {"undo_min": True},
        {"closed_grace": -1},
        {"closed_grace": 1.5},
        {"closed_grace": True},
    ],
)
def test_reask_undo_settings_are_checked(bad):
    with pytest.raises(SignalError):
        StallConfig(**bad)


def test_the_signal_keeps_no_takeover_of_its_own_it_reads_the_robots_control_state():
    """What a robot's takeovers were comes from its control state (``TriggerState.after_takeover``): the
    same steps with the operator's step told or not told decide differently, and the operator's steps
    themselves leave nothing in the signal."""

    def heading_back(after_takeover: bool) -> bool:
        signal = _undo_signal()
        for teleop, pos, to in ((False, [0, 0, 1.0], [0, 0, 1.0]), (True, [0.02, 0, 1.0], [0.01, 0, 1.0])):
            current = torch.as_tensor(_action(pos, OPEN))[None]
            batch = SignalInput(
                torch.zeros(1, 1, 26), current, np.asarray([0]), action=torch.as_tensor(_action(to, OPEN))[None, None]
            )
            signal.wants_help(signal.score(batch), TriggerState(np.asarray([0]), np.asarray([teleop])))
        current = torch.as_tensor(_action([0.02, 0, 1.0], OPEN))[None]
        plan = torch.as_tensor(_action([0.01, 0, 1.0], OPEN))[None, None]  # back towards where it asked
        batch = SignalInput(torch.zeros(1, 1, 26), current, np.asarray([0]), action=plan)
        state = TriggerState(np.asarray([0]), after_takeover=np.asarray([after_takeover]))
        return bool(signal.wants_help(signal.score(batch), state)[0])

    assert heading_back(after_takeover=True)  # told of the takeover: the plan undoes it, ask again
    assert not heading_back(after_takeover=False)  # not told: the signal kept no record of the operator's step

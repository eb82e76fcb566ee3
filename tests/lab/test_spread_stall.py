import numpy as np
import pytest
import torch

from lab.spread_stall import SpreadStallConfig
from policy.signals import SignalInput, TriggerState, load_signal, make_signal, save_signal
from policy.signals.base import CalibrationData, SignalError, StepSet
from sim.tasks.lift import LIFT_OBS
from tests.helpers import tiny_policy

OBS_DIM = LIFT_OBS.dim  # tiny_policy()'s observation: lift-cube's
OPEN, CLOSED = -1.0, 1.0
CALIBRATION = {
    "threshold": 1.0,
    "spread": {"threshold": 4.0, "spread_scale": 1.0},
    "stall": {"threshold": 0.5, "stride": 0.01},
}


def _action(pos, gripper=OPEN):
    return np.r_[pos, [0, 1, 0, 1, 0, 0], gripper].astype(np.float32)


def _signal(monkeypatch, **config):
    """A calibrated spread-stall whose field term and novelty this test sets (``feed``)."""
    signal = make_signal("spread-stall", tiny_policy(), SpreadStallConfig(patience=2, **config))
    signal.calibration = {k: dict(v) if isinstance(v, dict) else v for k, v in CALIBRATION.items()}
    field = {"spread": np.zeros(1), "novelty": np.zeros(1)}
    monkeypatch.setattr(signal.spread, "parts", lambda batch, box=None: {k: v.copy() for k, v in field.items()})

    def step(spread, novelty, motion, teleop=False):
        field["spread"][:], field["novelty"][:] = spread, novelty
        current = torch.as_tensor(_action([0, 0, 1]))[None]
        chunk = torch.as_tensor(_action([motion, 0, 1]))[None, None]
        scores = signal.score(SignalInput(torch.zeros(1, 1, OBS_DIM), current, np.asarray([0]), action=chunk))
        wants = signal.wants_help(scores, TriggerState(np.asarray([0]), np.asarray([teleop])))
        return scores, bool(wants[0])

    return signal, step


def test_on_a_familiar_scene_spread_asks_and_a_stall_does_not(monkeypatch):
    signal, step = _signal(monkeypatch)
    scores, wants = step(spread=2.0, novelty=0.0, motion=0.0)  # standing still, sure of itself
    assert not wants and scores.value[0] == pytest.approx(0.5)  # spread over its threshold of 4
    assert not step(spread=2.0, novelty=0.0, motion=0.0)[1]  # still after `patience` steps: no request
    scores, wants = step(spread=6.0, novelty=0.01, motion=0.02)  # moving, unsure
    assert wants and scores.value[0] == pytest.approx((6.0 + 0.01) / 4)  # spread's score: field + novelty
    assert scores.parts["new_scene"][0] == 0
    assert signal.explain(scores, 0).startswith("the policy is unsure")


def test_on_a_new_scene_only_a_stall_asks_until_the_episode_ends(monkeypatch):
    signal, step = _signal(monkeypatch, novelty_gate=0.05)
    scores, wants = step(spread=500.0, novelty=0.5, motion=0.02)  # new object: the field extrapolates
    assert not wants and scores.parts["new_scene"][0] == 1
    assert scores.value[0] == pytest.approx(0.0)  # moving at its stride: stillness 0
    scores, wants = step(spread=500.0, novelty=0.0, motion=0.0)  # novelty back in range: the scene stays new
    assert not wants and scores.value[0] == pytest.approx(2.0)  # stillness 1 over 0.5, first step of 2
    scores, wants = step(spread=0.0, novelty=0.0, motion=0.0)
    assert wants  # `patience` steps standing still
    assert signal.explain(scores, 0).startswith("new scene, the policy is stuck")
    signal.reset([0])
    scores, wants = step(spread=6.0, novelty=0.0, motion=0.0)  # the next episode starts familiar
    assert wants and scores.parts["new_scene"][0] == 0


def test_a_new_scene_keeps_the_operators_progress(monkeypatch):
    """reask_undo is on: after a takeover the policy that heads back to where it asked asks again."""
    signal, step = _signal(monkeypatch)
    step(spread=0.0, novelty=0.5, motion=0.0)
    assert step(spread=0.0, novelty=0.5, motion=0.0)[1]
    # it asked at x = 0; the operator drives it 3 cm across
    current = torch.as_tensor(_action([0.03, 0, 1]))[None]
    chunk = torch.as_tensor(_action([0.03, 0, 1]))[None, None]
    batch = SignalInput(torch.zeros(1, 1, OBS_DIM), current, np.asarray([0]), action=chunk)
    signal.wants_help(signal.score(batch), TriggerState(np.asarray([0]), np.asarray([True])))
    plan_back = torch.as_tensor(_action([0.015, 0, 1]))[None, None]
    back = SignalInput(torch.zeros(1, 1, OBS_DIM), current, np.asarray([0]), action=plan_back)
    scores = signal.score(back)
    after = TriggerState([0], after_takeover=np.asarray([True]))  # the control state: driven since
    assert signal.wants_help(scores, after)[0]
    assert signal.explain(scores, 0) == "new scene, the policy would undo the operator's work"
    assert signal.urgent(after)[0]  # a cooldown does not hold it back


def test_on_a_familiar_scene_no_request_is_urgent(monkeypatch):
    signal, step = _signal(monkeypatch)
    assert step(spread=6.0, novelty=0.0, motion=0.0)[1]
    assert not signal.urgent(TriggerState([0]))[0]


def test_the_sweep_scales_both_thresholds(monkeypatch):
    signal, step = _signal(monkeypatch)
    signal.calibration = {**signal.calibration, "threshold": 2.0}  # what `hitl bench hitl` sets
    assert not step(spread=6.0, novelty=0.0, motion=0.0)[1]  # 1.5x spread's threshold: under 2
    assert step(spread=9.0, novelty=0.0, motion=0.0)[1]


def test_wants_help_needs_the_scores_of_the_same_robots(monkeypatch):
    signal, step = _signal(monkeypatch)
    scores, _ = step(spread=1.0, novelty=0.0, motion=0.0)
    with pytest.raises(SignalError, match="same robots"):
        signal.wants_help(scores, TriggerState([7]))


def _steps(n=12):
    pos = np.stack([_action([0.01 * i, 0, 1]) for i in range(n)])
    return StepSet(
        obs=np.random.default_rng(0).uniform(-1, 1, (n, 1, OBS_DIM)).astype(np.float32),
        action=pos[:, None],
        current=pos,
        episode=np.zeros(n, dtype=np.int64),
        t=np.arange(n),
        last=np.arange(n) == n - 1,
        success=np.ones(n, dtype=bool),
        names=["ep0"],
    )


def test_calibration_records_both_signals_and_survives_a_save(tmp_path):
    policy = tiny_policy()
    signal = make_signal("spread-stall", policy, {"num_samples": 4})
    record = signal.calibrate(CalibrationData(train=_steps(), val=_steps()))
    assert record["threshold"] == 1.0
    assert record["spread"]["threshold"] > 0 and record["stall"]["stride"] > 0
    assert signal.spread.calibration is record["spread"] and signal.stall.calibration is record["stall"]
    save_signal(signal, tmp_path)
    loaded = load_signal(policy, tmp_path, "spread-stall")
    assert loaded.calibration == record and loaded.config == signal.config
    batch = SignalInput(torch.as_tensor(_steps().obs[:3]), torch.as_tensor(_steps().current[:3]), np.arange(3))
    np.testing.assert_allclose(loaded.score(batch).parts["spread"], signal.score(batch).parts["spread"], rtol=1e-5)


@pytest.mark.parametrize(
    "bad",
    [
        {"novelty_gate": 0},
        {"novelty_gate": float("nan")},
        {"novelty_gate": True},
        {"patience": 0},
        {"stall_quantile": 1.0},
        {"num_samples": 1},
        {"reask_undo": "yes"},
        {"spread_patience": 0},
        {"closed_grace": -1},
    ],
)
def test_settings_are_checked(bad):
    with pytest.raises((SignalError, ValueError)):
        SpreadStallConfig(**bad)


def test_a_threshold_of_zero_keeps_scores_finite(monkeypatch):
    """stall calibrates to 0 when the policy never stood still on the validation steps."""
    signal, step = _signal(monkeypatch)
    signal.calibration["stall"]["threshold"] = 0.0
    step(spread=0.0, novelty=0.5, motion=0.02)  # the scene is new; moving at its stride: 0 over
    scores, _ = step(spread=0.0, novelty=0.5, motion=0.0)
    assert np.isfinite(scores.value).all() and scores.value[0] > 1e6


def test_spread_patience_asks_after_that_many_steps_in_a_row(monkeypatch):
    signal, step = _signal(monkeypatch, spread_patience=2)
    assert not step(spread=6.0, novelty=0.0, motion=0.02)[1]  # one step over: a spike, no request
    assert not step(spread=1.0, novelty=0.0, motion=0.02)[1]
    assert not step(spread=6.0, novelty=0.0, motion=0.02)[1]
    assert step(spread=6.0, novelty=0.0, motion=0.02)[1]  # two in a row
    signal.reset([0])
    assert not step(spread=6.0, novelty=0.0, motion=0.02)[1]  # the count restarts with the episode


def test_an_episodes_level_is_what_patience_consecutive_steps_all_reach(monkeypatch):
    """Raising the asking half's threshold to an episode's level is exactly what keeps it from asking;
    the other half's threshold stays."""
    signal, step = _signal(monkeypatch, spread_patience=2)  # stall's patience: 2 as well (``_signal``)
    scores = [0.5, 1.6, 1.2, 0.3, 1.9, 0.2]  # the score over the threshold of 1, one per step
    assert signal.episode_level(np.asarray(scores), "familiar") == pytest.approx(1.2)  # steps 2-3 reach 1.2
    assert signal.episode_level(np.asarray([5.0]), "familiar") == 0.0  # shorter than the patience: never asks
    # spread's calibrated threshold is 4: raw spreads 4x the scores; the episode asks at its third step
    asked = [step(spread=4 * s, novelty=0.0, motion=0.02)[1] for s in scores]
    assert asked[2]
    signal.reset([0])
    signal.scale_threshold("familiar", 1.2, {"tasks": ["lift-cube"]})
    assert signal.calibration["spread"]["threshold"] == pytest.approx(4.8)
    assert signal.calibration["spread"]["demonstrations_threshold"] == 4.0
    assert signal.calibration["spread"]["own_episodes"] == {"tasks": ["lift-cube"], "factor": 1.2}
    assert signal.calibration["stall"]["threshold"] == 0.5
    assert not any(step(spread=4 * s, novelty=0.0, motion=0.02)[1] for s in scores)
    # a new scene: stall asks after 2 steps standing still (stillness 1 = 2x its threshold of 0.5)
    signal.reset([0])
    assert [step(spread=0.0, novelty=0.5, motion=0.0)[1] for _ in range(2)] == [False, True]
    signal.scale_threshold("new", 2.5, {"tasks": ["lift-hammer"]})
    assert signal.calibration["stall"]["threshold"] == pytest.approx(1.25)
    assert signal.calibration["spread"]["threshold"] == pytest.approx(4.8)
    signal.reset([0])
    assert not any(step(spread=0.0, novelty=0.5, motion=0.0)[1] for _ in range(4))
    for bad in (0.9, float("nan"), "2"):
        with pytest.raises(SignalError, match="only be raised"):
            signal.scale_threshold("familiar", bad, {})
    with pytest.raises(SignalError, match="scene must be one of"):
        signal.episode_level(np.zeros(3), "kitchen")


def test_the_lab_registers_spread_stall_only_inside_its_block(monkeypatch):
    """Superseded by choice-stall: the benchmarks name it while ``lab.signals.registered`` holds (``hitl``'s
    benchmark and experiment commands), the product's registry has it not."""
    from lab.signals import registered
    from lab.spread_stall import SpreadStallSignal
    from policy.signals.registry import SIGNALS

    monkeypatch.delitem(SIGNALS, "spread-stall")  # this module's fixture registered it
    with pytest.raises(KeyError, match="unknown signal 'spread-stall'"):
        make_signal("spread-stall", tiny_policy())
    with registered():
        assert SIGNALS["spread-stall"] is SpreadStallSignal
        with registered():
            pass
        assert "spread-stall" in SIGNALS  # an inner block leaves the outer one's
    assert "spread-stall" not in SIGNALS

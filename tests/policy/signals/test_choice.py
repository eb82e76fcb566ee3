import numpy as np
import pytest
import torch

from policy.hitl_state import RobotControl
from policy.signals import SignalInput, TriggerState, load_signal, make_signal, save_signal
from policy.signals.base import CalibrationData, SignalError, StepSet
from policy.signals.choice import IQR_TO_STD, ChoiceConfig, Hysteresis, reach, where_to_go
from policy.signals.choice_stall import ChoiceStallConfig
from sim.tasks.lift import LIFT_OBS
from tests.helpers import tiny_policy

OBS_DIM = LIFT_OBS.dim  # tiny_policy()'s observation: lift-cube's
OPEN = -1.0


def _chunks(positions: np.ndarray, chunk: int = 1, step: int = 0) -> torch.Tensor:
    """(B, S, 3) positions placed at chunk step ``step`` of (B, S, chunk, 10) chunks (zeros elsewhere)."""
    b, s, _ = positions.shape
    out = torch.zeros(b, s, chunk, 10, dtype=torch.float64)
    out[:, :, step, :3] = torch.as_tensor(positions)
    return out


def test_where_to_go_counts_the_spread_of_targets_on_both_sides_of_the_gripper():
    rng = np.random.default_rng(0)
    targets = np.zeros((3, 400, 3))
    targets[0, :, 1] = rng.choice([-0.03, 0.0, 0.03], size=400)  # three drawers across: a choice
    targets[1, :, :] = rng.normal(0, 0.001, size=(400, 3))  # one target, 1 mm of noise
    targets[2, :, 2] = rng.uniform(0.01, 0.05, size=400)  # all go up, by 1 to 5 cm: how far, not which way
    value = where_to_go(torch.as_tensor(targets), torch.zeros(3, 3)).numpy()
    q = np.quantile(targets[0, :, 1], [0.25, 0.75])
    assert value[0] == pytest.approx((q[1] - q[0]) / IQR_TO_STD)
    assert value[0] > 0.02 and value[1] < 0.002
    assert value[2] == 0.0
    assert where_to_go(torch.as_tensor(targets[2:]), torch.as_tensor([[0, 0, 0.03]])).item() > 0.01  # around it
    stray = targets[1].copy()
    stray[0] = [0.5, -0.5, 0.5]  # one sample half a metre off barely moves it
    assert where_to_go(torch.as_tensor(stray[None]), torch.zeros(1, 3)).item() < 0.002


def test_reach_reads_the_place_the_chunk_reaches():
    chunks = torch.zeros(1, 16, 4, 10, dtype=torch.float64)
    chunks[0, :, 2, 0] = torch.linspace(-0.05, 0.05, 16)  # executed steps: 3, so the third action is where it goes
    assert where_to_go(reach(chunks, 3), torch.zeros(1, 3)).item() > 0.02
    assert where_to_go(reach(chunks, 1), torch.zeros(1, 3)).item() == 0.0  # the first action agrees


def test_hysteresis_asks_over_the_ask_level_and_hands_back_under_the_return_level():
    h = Hysteresis(patience=2)
    ids = np.asarray([7])
    assert not h.update(np.asarray([True]), np.asarray([True]), ids)[0]  # one step over: patience is 2
    assert h.update(np.asarray([True]), np.asarray([True]), ids)[0]
    assert h.update(np.asarray([False]), np.asarray([True]), ids)[0]  # under the ask level, over the return level
    assert not h.update(np.asarray([False]), np.asarray([False]), ids)[0]  # under both: it hands back
    assert not h.update(np.asarray([False]), np.asarray([True]), ids)[0]  # the return level alone does not ask
    h.update(np.asarray([True]), np.asarray([True]), ids)
    h.reset([7])
    assert not h.update(np.asarray([True]), np.asarray([True]), ids)[0]  # a new episode starts the count again


def _choice(monkeypatch, name="choice", **config):
    """A calibrated signal whose where-to-go spread this test sets (``feed``)."""
    cfg = ChoiceConfig(**config) if name == "choice" else ChoiceStallConfig(**config)
    signal = make_signal(name, tiny_policy(), cfg)
    half = signal if name == "choice" else signal.choice
    spread = {"value": 0.0}
    monkeypatch.setattr(half, "spread", lambda obs, current, ids: np.full(len(ids), spread["value"]))
    return signal, spread


def _step(signal, teleop=False, motion=0.02, robot=0):
    current = torch.as_tensor(np.r_[[0, 0, 1], [0, 1, 0, 1, 0, 0], OPEN], dtype=torch.float32)[None]
    chunk = current.clone()[:, None]
    chunk[0, 0, 0] += motion
    batch = SignalInput(torch.zeros(1, 1, OBS_DIM), current, np.asarray([robot]), action=chunk)
    scores = signal.score(batch)
    return scores, bool(signal.wants_help(scores, TriggerState(np.asarray([robot]), np.asarray([teleop])))[0])


def test_choice_asks_once_and_asks_again_only_while_the_choice_stays_open(monkeypatch):
    signal, spread = _choice(monkeypatch, return_ratio=0.5)
    signal.calibration = {"threshold": 0.01}
    spread["value"] = 0.005
    assert not _step(signal)[1]
    spread["value"] = 0.015  # the targets disagree by 1.5 cm
    scores, wants = _step(signal)
    assert wants and "1.5 cm to either side" in signal.explain(scores, 0)
    spread["value"] = 0.007  # the operator's steps narrowed it, not below half the threshold
    assert _step(signal, teleop=True)[1]
    spread["value"] = 0.004  # settled: the robot hands back for good
    assert not _step(signal, teleop=True)[1]
    spread["value"] = 0.007
    assert not _step(signal)[1]


def test_choice_stall_asks_with_choice_on_a_familiar_scene_and_stall_on_a_new_one(monkeypatch):
    signal, spread = _choice(monkeypatch, name="choice-stall", patience=2, novelty_gate=0.05)
    low, span = np.zeros(OBS_DIM), np.ones(OBS_DIM)
    signal.calibration = {
        "threshold": 1.0,
        "novelty_range": {"low": low.tolist(), "span": span.tolist()},
        "choice": {"threshold": 0.01},
        "stall": {"threshold": 0.5, "stride": 0.01},
    }
    monkeypatch.setattr(signal.policy, "frame_obs", lambda obs: obs)
    spread["value"] = 0.02
    scores, wants = _step(signal, motion=0.0)  # standing still, but the scene is familiar: choice decides
    assert wants and scores.value[0] == pytest.approx(2.0) and scores.parts["new_scene"][0] == 0
    assert "choice of which way to go" in signal.explain(scores, 0)
    signal.reset([0])
    far = torch.full((1, 1, OBS_DIM), 2.0)  # outside the demonstrations' box by one range on every dimension
    current = torch.as_tensor(np.r_[[0, 0, 1], [0, 1, 0, 1, 0, 0], OPEN], dtype=torch.float32)[None]
    for k in range(2):
        batch = SignalInput(far, current, np.asarray([0]), action=current[:, None].clone())
        scores = signal.score(batch)
        wants = bool(signal.wants_help(scores, TriggerState(np.asarray([0]), np.asarray([False])))[0])
        assert scores.parts["new_scene"][0] == 1
        assert scores.value[0] == pytest.approx(2.0)  # stillness 1 over stall's 0.5, whatever choice says
        assert wants == (k == 1)  # stall's patience of 2
    assert signal.explain(scores, 0).startswith("new scene, the policy is stuck")


def test_choice_draws_each_robots_samples_from_its_own_stream():
    signal = make_signal("choice", tiny_policy(), ChoiceConfig(num_samples=8))
    obs = torch.randn(3, 1, OBS_DIM)
    together = signal.targets(obs, np.asarray([1, 2, 3]))
    signal.reset()
    alone = signal.targets(obs[1:2], np.asarray([2]))
    assert torch.allclose(alone[0], together[1], atol=1e-6)


def _steps(n=30):
    rng = np.random.default_rng(0)
    obs = rng.uniform(0, 1, (n, 1, OBS_DIM)).astype(np.float32)
    current = np.tile(np.r_[[0, 0, 1], [0, 1, 0, 1, 0, 0], OPEN], (n, 1)).astype(np.float32)
    action = current[:, None, :].copy()
    action[:, 0, 0] += 0.01
    episode = np.repeat(np.arange(3), n // 3)
    t = np.tile(np.arange(n // 3), 3)
    last = np.full(n, n // 3 - 1)
    return StepSet(obs, action, current, episode, t, last, np.ones(n, bool), ["a", "b", "c"])


def test_choice_stall_calibration_records_both_halves_and_survives_a_save(tmp_path):
    policy = tiny_policy()
    signal = make_signal("choice-stall", policy, ChoiceStallConfig(num_samples=8))
    cal = signal.calibrate(CalibrationData(_steps(), _steps()))
    assert cal["threshold"] == 1.0 and "stride" in cal["stall"]
    choice = cal["choice"]
    assert choice["stride"] > 0 and choice["threshold"] == pytest.approx(0.25 * choice["stride"])
    assert len(cal["novelty_range"]["low"]) == OBS_DIM
    save_signal(signal, tmp_path)
    loaded = load_signal(policy, tmp_path, "choice-stall")
    assert loaded.calibration == cal and loaded.config == signal.config


@pytest.mark.parametrize(
    "bad", [{"num_samples": 2}, {"return_ratio": 0.0}, {"return_ratio": 1.5}, {"stride_ratio": 0}, {"patience": 0}]
)
def test_choice_settings_are_checked(bad):
    with pytest.raises((SignalError, ValueError)):
        ChoiceConfig(**bad)


def test_agreement_compares_directions_and_the_gripper():
    from policy.signals.choice_stall import agrees

    def act(x, y=0.0, grip=OPEN):
        return np.r_[[x, y, 1.0], [0, 1, 0, 1, 0, 0], grip][None]

    here = act(0.0)
    assert agrees(act(0.01), act(0.03), here, 0.7, 0.003)[0]  # the same way, at different strides
    assert not agrees(act(0.01), act(-0.02), here, 0.7, 0.003)[0]  # opposite ways
    assert not agrees(act(0.01), act(0.01, 0.02), here, 0.7, 0.003)[0]  # 63 degrees apart
    assert not agrees(act(0.01, grip=1.0), act(0.02), here, 0.7, 0.003)[0]  # the policy would close the gripper
    assert agrees(act(0.001), act(0.0), here, 0.7, 0.003)[0]  # both hold still
    assert not agrees(act(0.001), act(0.02), here, 0.7, 0.003)[0]  # the operator moves, the policy holds


def test_choice_stall_asks_again_until_the_policy_agrees_with_the_operator(monkeypatch):
    signal, spread = _choice(monkeypatch, name="choice-stall")
    signal.calibration = {
        "threshold": 1.0,
        "choice": {"threshold": 0.01},
        "stall": {"threshold": 0.5, "stride": 0.01},
    }
    current = torch.as_tensor(np.r_[[0, 0, 1], [0, 1, 0, 1, 0, 0], OPEN], dtype=torch.float32)[None]

    control = RobotControl()  # robot 0's control state: the controller keeps the request's facts there

    def step(teleop=False, policy_dx=0.01, operator_dx=None):
        plan = current.clone()[:, None]
        plan[0, 0, 0] += policy_dx
        op = None
        if operator_dx is not None:
            op = current.clone()
            op[0, 0] += operator_dx
        batch = SignalInput(torch.zeros(1, 1, OBS_DIM), current, np.asarray([0]), action=plan, operator_action=op)
        scores = signal.score(batch)
        agreed = np.asarray([np.nan if control.agreed is None else float(control.agreed)])
        state = TriggerState(
            np.asarray([0]), np.asarray([teleop]), np.asarray([control.engaged]), agreed, np.asarray([control.driven])
        )
        wants = bool(signal.wants_help(scores, state)[0])
        if teleop:
            control.operator_step(True, wants, bool(scores.parts["agrees"][0] > 0), None)
        else:
            control.policy_step(wants)
        step.state = state
        return scores, wants

    spread["value"] = 0.02
    assert step()[1]  # the choice asks
    spread["value"] = 0.0  # the operator's steps settle the choice: its own score no longer asks
    assert step(teleop=True, policy_dx=0.01, operator_dx=-0.02)[1]  # but the policy would go the other way
    scores, wants = step()  # the first policy step after the takeover: ask again, to carry on
    assert wants and "carry on" in signal.explain(scores, 0)
    assert not signal.urgent(step.state)[0]  # a cooldown may hold it back
    assert not step(teleop=True, policy_dx=-0.01, operator_dx=-0.02)[1]  # now it agrees
    assert not step()[1]  # handed back for good
    spread["value"] = 0.007  # over the return level, under the ask level: the request was settled
    assert not step()[1]


def test_choice_stall_raises_the_asking_halfs_threshold_on_its_own_episodes():
    signal = make_signal("choice-stall", tiny_policy(), ChoiceStallConfig(patience=2))
    signal.calibration = {"threshold": 1.0, "choice": {"threshold": 0.004}, "stall": {"threshold": 0.5}}
    assert signal.episode_level(np.array([0.5, 3.0, 0.2]), "familiar") == 3.0  # choice asks at once
    assert signal.episode_level(np.array([0.5, 3.0, 0.2]), "new") == 0.5  # stall needs 2 steps in a row
    signal.scale_threshold("familiar", 2.0, {"episodes": 20})
    assert signal.calibration["choice"]["threshold"] == pytest.approx(0.008)
    assert signal.calibration["choice"]["demonstrations_threshold"] == 0.004
    assert signal.calibration["stall"] == {"threshold": 0.5}  # the other half is left as it is
    with pytest.raises(SignalError, match="only be raised"):
        signal.scale_threshold("new", 0.5, {})

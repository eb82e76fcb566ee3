import json

import numpy as np
import pytest
import torch

from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.signals import SIGNALS, SignalError, SignalInput, TriggerState, load_signal, make_signal, save_signal
from policy.signals.base import CalibrationData, Scores, StepSet
from policy.signals.sampling import rbf_mmd2

OBS_DIM, CHUNK = 4, 4
# what each signal calibrates on in ``tiny``'s data: 12 validation steps, 12 of the training steps
# (diff-dagger's subsample), 3 successful rollout episodes (stac), nothing (the references)
CALIBRATION_SAMPLES = {
    "denoising": 12,
    "output-variance": 12,
    "diff-dagger": 12,
    "thrifty": 12,
    "stac": 3,
    "hula-offline": 12,
    "spread": 12,
    "stall": None,  # the validation steps whose gripper is open now and in the policy's sampled action
    "choice": 12,
    "choice-stall": 12,  # choice's samples: every validation step
    "full-teleop": 0,
    "random": 0,
}
FAST = {  # keep every auxiliary training and calibration tiny
    "denoising": {"num_samples": 16, "max_modes": 2},
    "output-variance": {"num_samples": 8, "max_calibration_steps": 24},
    "diff-dagger": {"noise_draws": 2, "max_calibration_steps": 12},
    "thrifty": {"hidden": [16], "bc_steps": 30, "q_steps": 30},
    "stac": {"num_samples": 8},
    "hula-offline": {"hidden": [16], "steps": 30},
    "spread": {"num_samples": 8, "noise_step": 10},
    "stall": {"calibration_batch": 5},
    "choice": {"num_samples": 8},
    "choice-stall": {"num_samples": 8},
    "full-teleop": {},
    "random": {"rate": 0.5},
}


def _steps(n_episodes, length, seed, success=True, shift=0.0):
    rng = np.random.default_rng(seed)
    m = n_episodes * length
    obs = rng.uniform(0, 1, (m, 1, OBS_DIM)).astype(np.float32) + shift
    base = np.concatenate([obs[:, 0, :3], np.full((m, 6), 0.5), 2 * obs[:, 0, 3:4] - 1], axis=1)  # gripper ±1
    action = np.stack([base + 0.01 * c for c in range(CHUNK)], axis=1).astype(np.float32)
    return StepSet(
        obs=obs,
        action=action,
        current=base.astype(np.float32),
        episode=np.repeat(np.arange(n_episodes), length),
        t=np.tile(np.arange(length), n_episodes),
        last=np.full(m, length - 1),
        success=np.full(m, success) if isinstance(success, bool) else np.repeat(success, length),
        names=[f"ep{i}" for i in range(n_episodes)],
    )


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    cfg = DiffusionPolicyConfig(
        obs_dim=OBS_DIM,
        action_horizon=CHUNK,
        network="mlp",
        mlp_hidden=32,
        step_embed_dim=8,
        obs_encoder_dims=(16,),
        num_inference_steps=2,
    )
    policy = DiffusionPolicy(cfg)
    data = CalibrationData(
        train=_steps(6, 6, 0),
        val=_steps(2, 6, 1),
        rollouts=_steps(4, 6, 2, success=np.array([True, True, False, True])),
    )
    policy.fit_normalizers(data.train.obs[:, 0], data.train.action[:, 0])
    return policy.eval(), data


def _batch(data, rows, ids, operator=False):
    steps = data.val
    op = torch.as_tensor(steps.current[rows]) if operator else None
    return SignalInput(torch.as_tensor(steps.obs[rows]), torch.as_tensor(steps.current[rows]), ids, operator_action=op)


@pytest.mark.parametrize("name", list(SIGNALS))
def test_every_signal_calibrates_and_scores_a_tiny_policy(tiny, name, tmp_path):
    policy, data = tiny
    signal = make_signal(name, policy, FAST[name])
    if signal.has_models:
        signal.fit(data, progress=False)
    rec = signal.calibrate(data)
    want = CALIBRATION_SAMPLES[name]
    assert np.isfinite(rec["threshold"]) and (0 < rec["samples"] <= 12 if want is None else rec["samples"] == want)
    batch = _batch(data, np.arange(3), np.array([10, 11, 12]), operator=True)
    scores = signal.score(batch)
    assert scores.value.shape == (3,) and np.isfinite(scores.value).all()
    assert all(np.isfinite(v).all() for k, v in scores.parts.items() if k != "discrepancy")
    wants = signal.wants_help(scores, TriggerState([10, 11, 12]))
    assert wants.shape == (3,) and wants.dtype == bool
    signal.reset([10, 11, 12])
    # saved and loaded next to the policy, it scores the same
    save_signal(signal, tmp_path, {"command": "test"})
    doc = json.loads((tmp_path / "signals" / name / "config.json").read_text())
    assert doc["calibration"]["threshold"] == rec["threshold"]
    loaded = load_signal(policy, tmp_path, name)
    if name not in ("random",):
        signal.reset()
        loaded.reset()
        signal._generator.manual_seed(5)
        loaded._generator.manual_seed(5)
        if name == "denoising":
            signal.estimator.reset()
            loaded.estimator.reset()
        np.testing.assert_allclose(loaded.score(batch).value, signal.score(batch).value, rtol=1e-6)


class GaussianPolicy(DiffusionPolicy):
    """Analytic stand-in: actions ~ N(mean, std²) per dimension in a normalized space equal to the raw
    one, with obs[..., 0] = std and obs[..., 1] = mean; ε_θ is the exact noise of that distribution."""

    def __init__(self, chunk=CHUNK):
        super().__init__(
            DiffusionPolicyConfig(obs_dim=OBS_DIM, action_horizon=chunk, network="mlp", mlp_hidden=8, step_embed_dim=8)
        )
        self.fit_normalizers(np.array([[0.0] * OBS_DIM, [1.0] * OBS_DIM]), np.array([[0.0] * 10, [1.0] * 10]))

    @staticmethod
    def _params(obs):
        return obs[:, -1, 0], obs[:, -1, 1]

    def noise_prediction(self, obs, actions, k):
        std, mean = self._params(obs)
        ab = self.schedule.alphas_cumprod[torch.as_tensor(k).expand(obs.shape[0])]
        shape = (-1,) + (1,) * (actions.dim() - 1)
        ab, std, mean = ab.view(shape), std.view(shape), mean.view(shape)
        return (1 - ab).sqrt() * (actions - ab.sqrt() * mean) / (ab * std**2 + 1 - ab)

    def predict_action_chunk(self, obs, generator=None):
        std, mean = self._params(obs)
        noise = torch.randn((obs.shape[0], self.config.action_horizon, 10), generator=generator)
        return mean[:, None, None] + std[:, None, None] * noise


def _obs(std, mean):
    o = torch.zeros((len(std), 1, OBS_DIM))
    o[:, 0, 0], o[:, 0, 1] = torch.as_tensor(std), torch.as_tensor(mean)
    return o


def test_output_variance_is_higher_for_a_wider_action_distribution():
    signal = make_signal("output-variance", GaussianPolicy(), {"num_samples": 64})
    obs = _obs([0.01, 0.05, 0.2], [0.5, 0.5, 0.5])
    value = signal.score(SignalInput(obs, torch.full((3, 10), 0.5), np.arange(3))).value
    assert value[0] < value[1] < value[2]
    np.testing.assert_allclose(value, np.array([0.01, 0.05, 0.2]) ** 2, rtol=0.35)


def test_diff_dagger_loss_is_higher_off_the_data_manifold():
    policy = GaussianPolicy(chunk=1)
    signal = make_signal("diff-dagger", policy, {"noise_draws": 8})
    obs = _obs([0.05, 0.05], [0.5, 0.5])
    on = torch.full((1, 1, 10), 0.5)
    off = torch.full((1, 1, 10), 0.9)  # 8 standard deviations away
    loss = signal.diffusion_loss(obs, torch.cat([on, off])).numpy()
    assert loss[1] > 3 * loss[0]
    # the policy's own samples are on the manifold: about the same loss as the mean action
    sampled = signal.score(SignalInput(obs[:1], torch.full((1, 10), 0.5), np.array([0]))).value
    assert sampled[0] < loss[1] / 2


def test_stac_score_is_higher_when_consecutive_chunks_disagree():
    signal = make_signal("stac", GaussianPolicy(), {"num_samples": 64})
    current = torch.full((2, 10), 0.5)
    ids = np.array([0, 1])
    signal.score(SignalInput(_obs([0.05, 0.05], [0.5, 0.5]), current, ids))
    # robot 0 keeps its plan, robot 1's plan jumps
    s = signal.score(SignalInput(_obs([0.05, 0.05], [0.5, 0.8]), current, ids))
    assert s.parts["step"][1] > 10 * max(s.parts["step"][0], 1e-6)
    # cumulative over the episode: the score is the running sum of the per-step MMD²
    s2 = signal.score(SignalInput(_obs([0.05, 0.05], [0.5, 0.5]), current, ids))
    np.testing.assert_allclose(s2.value, s.value + s2.parts["step"])
    signal.reset([1])
    s3 = signal.score(SignalInput(_obs([0.05, 0.05], [0.5, 0.5]), current, ids))
    assert s3.parts["step"][1] == 0 and s3.value[1] == 0  # a reset robot starts a new episode


def test_stac_needs_a_chunked_policy(tmp_path):
    with pytest.raises(SignalError, match="action_horizon > 1"):
        make_signal("stac", GaussianPolicy(chunk=1))
    # loading says why it cannot work rather than asking for a training that would fail the same way
    with pytest.raises(SignalError, match="action_horizon > 1"):
        load_signal(GaussianPolicy(chunk=1), tmp_path, "stac")


def test_rbf_mmd_is_zero_for_identical_sets_and_grows_with_shift():
    g = torch.Generator().manual_seed(0)
    x = torch.randn((1, 64, 3), generator=g, dtype=torch.float64)
    assert float(rbf_mmd2(x, x)) == pytest.approx(0.0, abs=1e-12)
    near, far = rbf_mmd2(x, x + 0.1), rbf_mmd2(x, x + 3.0)
    assert float(far) > float(near) > 0


def test_ensemble_variance_is_higher_away_from_the_training_data(tiny):
    policy, data = tiny
    signal = make_signal("thrifty", policy, {"hidden": [32, 32], "bc_steps": 400, "q_steps": 20})
    signal.fit(data, progress=False)
    signal.calibrate(data)
    near = signal.score(_batch(data, np.arange(6), np.arange(6))).parts["novelty"]
    far_obs = torch.as_tensor(data.val.obs[:6]) + 3.0  # far outside the unit box the demos cover
    far = signal.score(SignalInput(far_obs, torch.as_tensor(data.val.current[:6]), np.arange(6))).parts["novelty"]
    assert np.median(far) > 10 * np.median(near)


def test_diff_dagger_patience_needs_consecutive_steps(tiny):
    signal = make_signal("diff-dagger", tiny[0])
    signal.calibration = {"threshold": 1.0}
    state = TriggerState([7, 8])
    seq = [[2.0, 2.0], [0.5, 2.0], [2.0, 2.0], [2.0, 0.5]]
    got = [signal.wants_help(Scores(np.array(v)), state).tolist() for v in seq]
    assert got == [[False, False], [False, True], [False, True], [True, False]]
    signal.reset([7])
    assert signal.wants_help(Scores(np.array([2.0, 2.0])), state).tolist() == [False, False]


def test_thrifty_switches_back_only_when_actions_agree_and_it_is_safe(tiny):
    signal = make_signal("thrifty", tiny[0])
    signal.calibration = {
        "threshold": 1.0,
        "novelty_threshold": 1.0,
        "risk_threshold": 0.5,
        "switch_back_discrepancy": 0.1,
        "switch_back_safety": 0.6,
    }
    parts = {
        "novelty": np.array([0.1, 0.1, 0.1, 0.1]),
        "risk": np.array([0.2, 0.2, 0.7, 0.2]),  # safety 0.8, 0.8, 0.3, 0.8
        "discrepancy": np.array([0.05, 0.5, 0.05, np.nan]),
    }
    scores = Scores(np.array([0.4, 0.4, 1.4, 0.4]), parts)
    teleop = TriggerState(np.arange(4), np.ones(4, dtype=bool))
    # under teleop: keeps asking unless actions agree and safety is high; no operator action: keeps asking
    assert signal.wants_help(scores, teleop).tolist() == [False, True, True, True]
    auto = TriggerState(range(4))
    assert signal.wants_help(scores, auto).tolist() == [False, False, True, False]


def test_random_asks_at_its_rate(tiny):
    signal = make_signal("random", tiny[0], {"rate": 0.2, "seed": 3})
    ids = np.arange(1000)
    asks = signal.wants_help(
        signal.score(SignalInput(torch.zeros(1000, 1, OBS_DIM), torch.zeros(1000, 10), ids)),
        TriggerState(ids),
    )
    assert 0.16 < asks.mean() < 0.24
    signal.match_rate(0.0)
    assert not signal.wants_help(Scores(np.array([0.999])), TriggerState([0])).any()


@pytest.mark.parametrize(
    ("name", "config", "match"),
    [
        ("output-variance", {"num_samples": 1}, "num_samples"),
        ("diff-dagger", {"quantile": 1.5}, "quantile"),
        ("thrifty", {"members": 1}, "members"),
        ("hula-offline", {"gamma": 1.0}, "gamma"),
        ("random", {"rate": float("nan")}, "rate"),
        ("denoising", {"backend": "gpu"}, "backend"),
        ("stac", {"bogus": 1}, "unknown"),
        ("spread", {"noise_step": 0}, "noise_step"),
        ("spread", {"dims": "xyz"}, "dims"),
        ("spread", {"novelty_weight": -1}, "novelty_weight"),
        ("denoising", {"center": "goal"}, "center"),
        ("denoising", {"directions": "signed"}, "directions"),
    ],
)
def test_signal_config_errors_name_the_bad_value(tiny, name, config, match):
    with pytest.raises(ValueError, match=match):
        make_signal(name, tiny[0], config)


def test_unknown_signal_and_missing_files_get_clear_errors(tiny, tmp_path):
    with pytest.raises(KeyError, match="registered signals"):
        make_signal("nope", tiny[0])
    with pytest.raises(SignalError, match="hitl train-signal"):
        load_signal(tiny[0], tmp_path, "thrifty")
    signal = make_signal("hula-offline", tiny[0], FAST["hula-offline"])
    with pytest.raises(SignalError, match="no trained models"):
        signal.calibrate(tiny[1])
    with pytest.raises(SignalError, match="rollouts"):
        signal.calibrate(CalibrationData(tiny[1].train, tiny[1].val))


def test_train_signal_command_calibrates_on_the_policys_validation_split(tmp_path, capsys):
    from hitl.cli import main
    from policy.checkpoint import save_policy
    from storage import keys
    from storage.dataset import DatasetConfig, load_dataset
    from storage.episodes import EpisodeWriter

    rng = np.random.default_rng(0)
    demos = tmp_path / "demos"
    for i, n in enumerate([6, 7, 8, 9, 10]):
        w = EpisodeWriter(demos / f"ep{i:02d}.mcap", {"task": "unit", "seed": i}, object_names=[])
        for t in range(n):
            act = np.r_[rng.uniform(-0.1, 0.1, 3), [0, 1, 0, -1, 0, 0], [-1.0]]
            quat = np.array([1.0, 0, 0, 0])
            w.write_step(t, rng.normal(size=OBS_DIM), act, act[:3], quat, 0.04, t == n - 1, keys.SOURCE_EXPERT, {})
        w.finish(True, n, "success")
    ds = load_dataset(demos, DatasetConfig())
    train, val = ds.split()
    torch.manual_seed(0)
    policy = DiffusionPolicy(
        DiffusionPolicyConfig(obs_dim=OBS_DIM, network="mlp", mlp_hidden=16, step_embed_dim=8, num_inference_steps=2)
    )
    policy.fit_normalizers(ds.obs, ds.actions)
    split = {"train_episodes": [ds.names[i] for i in train], "val_episodes": [ds.names[i] for i in val]}
    save_policy(policy, tmp_path / "policy", {"task": "lift-cube", "dataset": split})
    args = ["train-signal", "--policy", str(tmp_path / "policy"), "--data", str(demos), "--quiet"]
    assert main([*args, "--signal", "output-variance", "--set", "num_samples=4"]) == 0
    out = json.loads(capsys.readouterr().out)
    val_steps = sum(
        int(e - s)
        for s, e, n in zip(ds.episode_starts, ds.episode_ends, ds.names, strict=True)
        if n in split["val_episodes"]
    )
    assert out["calibration"]["samples"] == val_steps and np.isfinite(out["calibration"]["threshold"])
    assert (tmp_path / "policy" / "signals" / "output-variance" / "config.json").is_file()
    assert main([*args, "--signal", "nope"]) == 2
    assert main([*args, "--signal", "output-variance", "--set", "num_samples=1"]) == 2
    assert "num_samples" in capsys.readouterr().err


def test_the_denoising_fallback_serves_the_settings_it_was_calibrated_with(tiny, tmp_path):
    from policy.checkpoint import save_calibration

    policy, _ = tiny
    save_calibration(tmp_path, {"threshold": 0.3, "uncertainty": {"num_samples": 16, "radius": 0.02, "max_modes": 2}})
    signal = load_signal(policy, tmp_path, "denoising")
    assert signal.threshold == 0.3
    cfg = signal.estimator.config
    assert (cfg.num_samples, cfg.radius, cfg.max_modes) == (16, 0.02, 2)
    save_calibration(tmp_path, {"threshold": 0.3, "uncertainty": {"radius": 7}})
    with pytest.raises(SignalError, match="radius"):
        load_signal(policy, tmp_path, "denoising")


def test_spread_matches_the_gaussian_posterior_and_grows_with_the_policys_spread():
    """For N(mean, std²) the re-noised estimates spread by (1-ᾱ)/ᾱ · (ᾱ std² / (ᾱ std² + 1 - ᾱ))²: more for a
    wider policy, where the paper's Var_g at k = 0 shrinks."""
    from policy.signals.spread import renoised_estimates

    policy = GaussianPolicy(chunk=1)
    k = 30
    ab = float(policy.schedule.alphas_cumprod[k])
    std = torch.tensor([0.02, 0.05, 0.1])
    obs = _obs(std, torch.full((3,), 0.5))
    center = torch.full((3, 1, 10), 0.5)
    xi = torch.randn((3, 20000, 1, 10), generator=torch.Generator().manual_seed(0))
    x0 = renoised_estimates(policy.noise_prediction, obs, center, ab, k, xi)
    measured = x0.var(dim=1, unbiased=False).mean(dim=(1, 2))
    expected = (1 - ab) / ab * (ab * std**2 / (ab * std**2 + 1 - ab)) ** 2
    np.testing.assert_allclose(measured.numpy(), expected.numpy(), rtol=0.03)
    signal = make_signal("spread", policy, {"num_samples": 256, "noise_step": k, "novelty_weight": 0.0})
    parts = signal.parts(SignalInput(obs, center[:, 0], np.arange(3), action=center))
    assert parts["spread"][0] < parts["spread"][1] < parts["spread"][2]
    assert np.allclose(parts["novelty"], 0.0)  # observations inside the normalizer's range
    denoising = make_signal("denoising", policy, {"num_samples": 64, "max_modes": 1})
    var_g = denoising.score(SignalInput(obs, center[:, 0], np.arange(3))).parts["var_g"]
    assert var_g[0] > var_g[1] > var_g[2]  # the paper's term rewards the sharper policy


def test_spread_novelty_counts_only_what_lies_outside_the_training_range(tiny):
    from policy.signals.spread import observation_novelty

    normalized = torch.tensor([[[0.5, 0.0, 1.0, 0.2]], [[1.5, -0.5, 0.5, 0.5]]])
    np.testing.assert_allclose(observation_novelty(normalized).numpy(), [0.0, (0.5 + 0.5) / 4])


def test_spread_measures_novelty_against_the_demonstrations_it_was_calibrated_on(tiny):
    """The calibration records the training demonstrations' box; a policy fitted on them gives the same
    novelty against its normalizer. Widening the normalizer to unseen observations (as fine-tuning on
    takeovers does) leaves them new to the signal, and a saved calibration keeps the box."""
    import copy

    from policy.signals.spread import novelty_against

    policy, data = tiny
    signal = make_signal("spread", policy, FAST["spread"])
    record = signal.calibrate(data)
    box = record["novelty_range"]
    np.testing.assert_allclose(box["low"], policy.obs_normalizer.low.numpy(), rtol=1e-6)
    np.testing.assert_allclose(box["span"], policy.obs_normalizer.span.numpy(), rtol=1e-6)
    unseen = torch.as_tensor(data.val.obs[:3]) + torch.tensor([2.0, 0.0, 0.0, 0.0])  # one dimension 2 units out
    before = novelty_against(policy, unseen, None).numpy()
    assert (before > 0.2).all()
    widened = copy.deepcopy(policy)
    assert widened.widen_obs_range(unseen.numpy()) == 1
    assert np.allclose(novelty_against(widened, unseen, None).numpy(), 0.0)  # the network's range now covers it
    np.testing.assert_allclose(novelty_against(widened, unseen, box).numpy(), before, rtol=1e-5)
    child = make_signal("spread", widened, FAST["spread"])
    child.calibration = json.loads(json.dumps(record))  # as saved and loaded
    action = torch.as_tensor(data.val.action[:3])
    scored = child.score(SignalInput(unseen, torch.as_tensor(data.val.current[:3]), np.arange(3), action=action))
    np.testing.assert_allclose(scored.parts["novelty"], before, rtol=1e-5)
    with pytest.raises(SignalError, match="novelty_range"):
        novelty_against(policy, unseen, {"low": [0.0], "span": [1.0]})


def test_spread_draws_each_robots_noise_from_its_own_stream(tiny):
    """A robot's score does not depend on which robots share its batch, or where it sits in it."""
    policy, data = tiny
    signal = make_signal("spread", policy, {"num_samples": 8, "noise_step": 10})
    rows = np.arange(4)
    action = torch.as_tensor(data.val.action[rows])
    full = signal.score(SignalInput(data.val.obs[rows], data.val.current[rows], np.array([7, 8, 9, 10]), action=action))
    signal.reset()
    alone = signal.score(SignalInput(data.val.obs[2:3], data.val.current[2:3], np.array([9]), action=action[2:3]))
    np.testing.assert_allclose(alone.parts["spread"], full.parts["spread"][2:3], rtol=1e-5)


def test_the_paper_metric_on_a_chunk_probes_where_the_chunk_will_reach(tiny):
    """``center = "chunk"``: the probe is the policy's chunk moved by the ball's offsets, read at the chunk's
    last executed step; its samples lie around that step's pose, not around the current one."""
    policy, data = tiny
    signal = make_signal("denoising", policy, {"num_samples": 16, "max_modes": 2, "center": "chunk"})
    last = min(policy.config.n_action_steps, policy.config.action_horizon) - 1
    assert signal.estimator.config.chunk_step == last
    batch = _batch(data, np.arange(2), np.array([1, 2]))
    plan = torch.as_tensor(data.val.action[:2]).clone()
    plan[:, last, :3] += 0.3  # the chunk goes 30 cm away from where it starts
    batch.action = plan
    result = signal.score(batch).detail
    reached = policy.normalize_action(plan)[:, last, :3].double()
    assert torch.allclose(result.samples.mean(dim=1), reached, atol=0.05)
    assert np.isfinite(signal.score(batch).value).all()

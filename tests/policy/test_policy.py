import json

import numpy as np
import pytest
import torch

from policy.checkpoint import CheckpointError, load_policy, save_policy
from policy.config import DiffusionPolicyConfig
from policy.diffusion import NoiseSchedule
from policy.diffusion_policy import DiffusionPolicy
from policy.train import TrainConfig, train_policy
from storage import keys
from tests.helpers import state_equal

OBS_DIM = 7


def _toy_data(n=256, horizon=1, chunk=1, seed=0):
    """Actions are a deterministic function of the observation, so the loss can fall."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, size=(n, horizon, OBS_DIM)).astype(np.float32)
    base = np.concatenate([obs[:, -1, :3], np.tanh(obs[:, -1, 3:7]), obs[:, -1, :3]], axis=1)  # (n, 10)
    act = np.stack([base + 0.01 * c for c in range(chunk)], axis=1).astype(np.float32)
    return {keys.OBS: obs, keys.ACTION: act}


def _policy(network="mlp", horizon=1, chunk=1, n_action_steps=None, **kw):
    torch.manual_seed(0)
    cfg = DiffusionPolicyConfig(
        obs_dim=OBS_DIM,
        obs_horizon=horizon,
        action_horizon=chunk,
        n_action_steps=n_action_steps,
        network=network,
        down_dims=(16, 32),
        n_groups=4,
        step_embed_dim=16,
        mlp_hidden=64,
        obs_encoder_dims=(32,),
        num_inference_steps=5,
        **kw,
    )
    return DiffusionPolicy(cfg)


@pytest.mark.parametrize(
    ("network", "horizon", "chunk", "octaves"),
    [("mlp", 1, 1, 0), ("unet", 1, 1, 0), ("unet", 2, 8, 0), ("mlp", 2, 8, 0), ("unet", 1, 1, 3)],
)
def test_training_reduces_loss_and_shapes_are_right(network, horizon, chunk, octaves):
    data = _toy_data(horizon=horizon, chunk=chunk)
    policy = _policy(network, horizon, chunk, obs_fourier_octaves=octaves)
    policy.fit_normalizers(data[keys.OBS], data[keys.ACTION])
    with torch.no_grad():
        before = float(
            policy.compute_loss(
                {k: torch.as_tensor(v) for k, v in data.items()}, generator=torch.Generator().manual_seed(1)
            )
        )
    ema, history = train_policy(
        policy,
        data,
        None,
        TrainConfig(steps=300, batch_size=64, warmup_steps=10, lr=3e-3, ema_decay=0.9),
        progress=False,
    )
    with torch.no_grad():
        after = float(
            ema.compute_loss(
                {k: torch.as_tensor(v) for k, v in data.items()}, generator=torch.Generator().manual_seed(1)
            )
        )
    assert np.isfinite(after) and after < 0.7 * before
    obs = torch.as_tensor(data[keys.OBS][:5])
    chunk_out = ema.predict_action_chunk(obs)
    assert chunk_out.shape == (5, chunk, 10) and torch.isfinite(chunk_out).all()
    probe = torch.rand(5, 3, chunk, 10)
    eps = ema.noise_prediction(obs, probe, 0)
    assert eps.shape == probe.shape and torch.isfinite(eps).all()
    assert ema.noise_prediction(obs, probe[:, 0], torch.zeros(5, dtype=torch.long)).shape == (5, chunk, 10)


def test_noise_prediction_broadcasts_the_observation_over_samples():
    policy = _policy("unet")
    obs = torch.randn(3, 1, OBS_DIM)
    probe = torch.rand(3, 4, 1, 10)
    together = policy.noise_prediction(obs, probe, 0)
    one_by_one = torch.stack([policy.noise_prediction(obs, probe[:, m], 0) for m in range(4)], dim=1)
    torch.testing.assert_close(together, one_by_one, rtol=1e-5, atol=1e-5)


def test_select_action_owns_the_queues():
    policy = _policy("mlp", horizon=2, chunk=8, n_action_steps=4)
    policy.fit_normalizers(np.random.default_rng(0).normal(size=(50, OBS_DIM)), np.random.rand(50, 10))
    calls = []
    original = policy.predict_action_chunk
    policy.predict_action_chunk = lambda obs: calls.append(obs.clone()) or original(obs)
    obs = torch.randn(2, OBS_DIM)
    for t in range(9):
        assert policy.select_action(obs + t).shape == (2, 10)
    assert len(calls) == 3  # steps 0, 4 and 8
    # the history is padded with the first frame, then slides
    torch.testing.assert_close(calls[0][:, 0], obs)
    torch.testing.assert_close(calls[1][:, 0], obs + 3)
    torch.testing.assert_close(calls[1][:, 1], obs + 4)
    policy.reset()
    policy.select_action(obs)
    assert len(calls) == 4


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    data = _toy_data(chunk=8, horizon=2)
    policy = _policy("unet", horizon=2, chunk=8)
    policy.fit_normalizers(data[keys.OBS], data[keys.ACTION])
    policy, _ = train_policy(policy, data, None, TrainConfig(steps=20, batch_size=32, warmup_steps=2), progress=False)
    save_policy(policy, tmp_path / "p", {"task": "unit", "command": "hitl train ..."})
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["config.json", "model.safetensors"]
    doc = json.loads((tmp_path / "p" / "config.json").read_text())
    assert doc["normalization"]["action"]["min"] == pytest.approx(data[keys.ACTION].reshape(-1, 10).min(0).tolist())
    loaded, info = load_policy(tmp_path / "p")
    assert info["task"] == "unit" and state_equal(policy, loaded)
    obs = torch.as_tensor(data[keys.OBS][:6])
    a = policy.predict_action_chunk(obs, generator=torch.Generator().manual_seed(3))
    b = loaded.predict_action_chunk(obs, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, b)


@pytest.mark.parametrize(("network", "horizon", "chunk"), [("unet", 1, 1), ("unet", 2, 8), ("mlp", 1, 1)])
def test_frozen_inference_gives_the_same_outputs_and_never_trains(network, horizon, chunk):
    data = _toy_data(horizon=horizon, chunk=chunk)
    policy = _policy(network, horizon, chunk)
    policy.fit_normalizers(data[keys.OBS], data[keys.ACTION])
    policy.eval()
    obs = torch.as_tensor(data[keys.OBS][:5])
    probe = torch.rand(5, 16, chunk, 10)
    eager_actions = policy.predict_action_chunk(obs, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        eager_eps = policy.noise_prediction(obs, probe, 0)
    keys_before = set(policy.state_dict())
    policy.freeze_for_inference()
    assert set(policy.state_dict()) == keys_before  # the traced copy is not part of the checkpoint
    traced_actions = policy.predict_action_chunk(obs, generator=torch.Generator().manual_seed(3))
    # on CPU the trace runs oneDNN's linear layers: float32 sums in another order, so agreement to a
    # few 1e-6 (the eager module differs from itself by ~1e-6 between batch sizes)
    close = {"rtol": 1e-5, "atol": 5e-6}
    with torch.no_grad():  # other batch sizes and sample counts than the trace saw
        torch.testing.assert_close(policy.noise_prediction(obs, probe, 0), eager_eps, **close)
        one = policy.noise_prediction(obs[:1], probe[:1, :3], 0)
        torch.testing.assert_close(one, eager_eps[:1, :3], **close)
    torch.testing.assert_close(traced_actions, eager_actions, **close)
    # gradients still flow through the module itself, and training drops the stale copy
    loss = policy.compute_loss({k: torch.as_tensor(v[:8]) for k, v in data.items()})
    loss.backward()
    assert all(p.grad is not None for p in policy.net.parameters() if p.requires_grad)
    with torch.no_grad():
        for param in policy.net.parameters():
            param.add_(0.1)
    policy.train()
    policy.eval()
    with torch.no_grad():
        assert not torch.allclose(policy.noise_prediction(obs, probe, 0), eager_eps)
    with pytest.raises(RuntimeError, match="eval mode"):
        policy.train().freeze_for_inference()


def test_bad_checkpoints_get_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="config.json not found"):
        load_policy(tmp_path)
    save_policy(_policy(), tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CheckpointError, match="cannot load weights"):
        load_policy(tmp_path)
    (tmp_path / "config.json").write_text("{broken")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_policy(tmp_path)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"action_horizon": 0}, "action_horizon"),
        ({"network": "transformer"}, "network"),
        ({"n_action_steps": 9, "action_horizon": 8}, "n_action_steps"),
        ({"down_dims": (30,)}, "n_groups"),
        ({"num_inference_steps": 200}, "num_inference_steps"),
        ({"obs_fourier_octaves": 9}, "obs_fourier_octaves"),
        ({"obs_fourier_octaves": 2, "obs_encoder_dims": ()}, "obs_encoder_dims"),
    ],
)
def test_config_errors_name_the_bad_value(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DiffusionPolicyConfig(obs_dim=OBS_DIM, **kwargs)


def test_schedule_golden_values():
    s = NoiseSchedule(100)
    # squared-cosine schedule: alpha_bar starts near 1 and ends near 0
    assert float(s.alphas_cumprod[0]) == pytest.approx(0.999369, abs=1e-6)  # cos² ratio at t = 0.01
    assert float(s.alphas_cumprod[-1]) < 1e-3
    assert s.ddim_timesteps(10) == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    # DDIM with the true noise recovers x0 exactly (no clipping)
    x0 = torch.rand(4, 1, 10)
    eps = torch.randn(4, 1, 10)
    k = 60
    xk = s.add_noise(x0, eps, torch.full((4,), k))
    torch.testing.assert_close(s.ddim_step(xk, eps, k, -1), x0, rtol=1e-4, atol=1e-5)


def test_symmetry_augmentation_turns_each_sample_and_needs_a_symmetry():
    data = _toy_data()
    policy = _policy("mlp")
    policy.fit_normalizers(data[keys.OBS], data[keys.ACTION])
    cfg = TrainConfig(steps=5, batch_size=16, warmup_steps=1, symmetry_augment=True)
    with pytest.raises(ValueError, match="symmetry"):
        train_policy(policy, data, None, cfg, progress=False)
    seen = []

    def flip(obs, k):  # a two-fold "symmetry" that negates the first observation dim on turn 1
        seen.append(k.copy())
        out = obs.copy()
        out[..., 0] = np.where(k == 1, -obs[..., 0], obs[..., 0])
        return out

    _, history = train_policy(policy, data, None, cfg, progress=False, symmetry=flip, symmetry_order=2)
    turns = np.concatenate(seen)
    assert len(seen) == 5 and turns.shape == (80, 1) and set(np.unique(turns)) == {0, 1}
    assert all(np.isfinite(history["train_loss"]))


def test_actions_normalize_over_the_task_bounds_not_the_data():
    """Rotation and gripper over [-1, 1] and position over the workspace: data that spans a sliver of
    a dimension cannot stretch it, so a probe radius means the same distance in every policy."""
    from sim.tasks.lift import LIFT_WORKSPACE

    space = LIFT_WORKSPACE
    rng = np.random.default_rng(0)
    # a rotation that barely varies in the data (the drawer's case): span 0.002
    acts = np.concatenate(
        [rng.uniform([-0.1, -0.1, 0.9], [0.1, 0.1, 1.0], (64, 3)), np.tile([0, 1, 0, 1, 0, 0, -1], (64, 1))], 1
    )
    acts[:, 3] += rng.uniform(-0.001, 0.001, 64)
    policy = DiffusionPolicy(DiffusionPolicyConfig(obs_dim=4, network="mlp", mlp_hidden=16, step_embed_dim=8))
    policy.fit_normalizers(rng.normal(size=(64, 4)), acts, action_bounds=(space.low, space.high))
    np.testing.assert_allclose(policy.normalize_action(torch.as_tensor(space.low)).numpy(), 0.0, atol=1e-6)
    np.testing.assert_allclose(policy.normalize_action(torch.as_tensor(space.high)).numpy(), 1.0, atol=1e-6)
    np.testing.assert_allclose(
        policy.normalize_action(torch.as_tensor(acts[:5])).numpy(), space.normalize(acts[:5]), atol=1e-6
    )
    # a real end-effector rotation 0.15 rad off the data's: 0.037 units, not the dozens a data span gives
    turned = acts[:1].copy()
    turned[0, 3:9] = [np.sin(0.15), np.cos(0.15), 0, np.cos(0.15), -np.sin(0.15), 0]
    shift = policy.normalize_action(torch.as_tensor(turned)) - policy.normalize_action(torch.as_tensor(acts[:1]))
    assert float(shift.abs().max()) < 0.1
    data_fit = DiffusionPolicy(DiffusionPolicyConfig(obs_dim=4, network="mlp", mlp_hidden=16, step_embed_dim=8))
    data_fit.fit_normalizers(rng.normal(size=(64, 4)), acts)
    shift = data_fit.normalize_action(torch.as_tensor(turned)) - data_fit.normalize_action(torch.as_tensor(acts[:1]))
    assert float(shift.abs().max()) > 10
    # training actions outside the bounds are refused, by dimension
    bad = acts.copy()
    bad[3, 0] = 0.5
    with pytest.raises(ValueError, match=r"1 training actions lie outside the action bounds in dims \[0\]"):
        policy.fit_normalizers(rng.normal(size=(64, 4)), bad, action_bounds=(space.low, space.high))
    with pytest.raises(ValueError, match="low < high"):
        policy.action_normalizer.set_bounds(space.high, space.low)
    with pytest.raises(ValueError, match="10 values"):
        policy.action_normalizer.set_bounds(space.low[:3], space.high[:3])


@pytest.mark.parametrize("length", [1, 4])
def test_group_norm_fast_path_matches_torch_group_norm_with_gradients(length):
    from policy.networks import _GroupNorm

    torch.manual_seed(0)
    ref, fast = torch.nn.GroupNorm(8, 64), _GroupNorm(8, 64)
    with torch.no_grad():
        ref.weight.normal_()
        ref.bias.normal_()
    fast.load_state_dict(ref.state_dict())
    x = (torch.randn(300, 64, length) * 3 + 1).requires_grad_()
    y = x.detach().clone().requires_grad_()
    torch.testing.assert_close(fast(x), ref(y), rtol=1e-5, atol=1e-5)
    fast(x).square().sum().backward()
    ref(y).square().sum().backward()
    torch.testing.assert_close(x.grad, y.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fast.weight.grad, ref.weight.grad, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("network", ["unet", "mlp"])
def test_the_network_path_creates_no_tensor_off_the_policy_device(network):
    """Device-agnostic serving, checked without an accelerator: on PyTorch's ``meta`` device any CPU tensor
    mixed into the computation raises, so a policy moved there must answer meta inputs on meta."""
    policy = _policy(network).eval()
    policy.to("meta")
    assert policy.device.type == "meta"
    obs = torch.zeros((3, 1, OBS_DIM), device="meta")
    with torch.no_grad():
        eps = policy.noise_prediction(obs, torch.zeros((3, 5, 1, 10), device="meta"), 0)
        chunk = policy.predict_action_chunk(obs, noise=torch.zeros((3, 1, 10), device="meta"))
    assert eps.device.type == "meta" and eps.shape == (3, 5, 1, 10)
    assert chunk.device.type == "meta" and chunk.shape == (3, 1, 10)


def test_a_policy_answers_on_the_device_of_its_input():
    policy = _policy("unet").eval()
    obs = torch.zeros((2, 1, OBS_DIM))
    with torch.no_grad():
        chunk = policy.predict_action_chunk(obs, noise=torch.zeros((2, 1, 10)))
        eps = policy.noise_prediction(obs, torch.zeros((2, 4, 1, 10)), 0)
    assert policy.device.type == "cpu" and chunk.device == obs.device and eps.device == obs.device


def test_widening_a_normalizer_covers_new_data_and_keeps_the_rest_exact():
    from policy.normalizer import MinMaxNormalizer

    norm = MinMaxNormalizer(3).fit(np.array([[0.0, 0.0, 5.0], [1.0, 2.0, 5.0]]))
    before = norm.normalize(torch.tensor([0.5, 1.0, 5.0]))
    assert norm.widen(np.array([[0.5, -2.0, 5.0], [0.2, 1.0, 5.0]])) == 1  # only dim 1 leaves the range
    assert norm.stats() == {"min": [0.0, -2.0, pytest.approx(4.9995)], "max": [1.0, 2.0, pytest.approx(5.0005)]}
    after = norm.normalize(torch.tensor([0.5, 1.0, 5.0]))
    assert after[0] == before[0] and after[2] == before[2] and after[1] == 0.75  # dim 1: (1 - -2) / 4
    assert norm.widen(np.zeros((0, 3))) == 0
    with pytest.raises(ValueError, match="NaN or inf"):
        norm.widen(np.array([[np.nan, 0.0, 0.0]]))
    # the data it was fitted to is inside, even where low + span rounds below the data's maximum
    data = np.random.default_rng(0).normal(0.3, 0.7, size=(200, 16)).astype(np.float32)
    fitted = MinMaxNormalizer(16).fit(data)
    low, span = fitted.low.clone(), fitted.span.clone()
    assert fitted.widen(data) == 0 and torch.equal(fitted.low, low) and torch.equal(fitted.span, span)

"""Policies that see cameras: the encoder, crops, the seen observation, encoding once per robot-step."""

import numpy as np
import pytest
import torch

from policy.config import DiffusionPolicyConfig
from policy.controller import Controller
from policy.diffusion_policy import DiffusionPolicy
from policy.signals import make_signal
from policy.vision import SpatialSoftmax, crop_frames
from sim.env import ROBOT_OBS
from sim.frame import RobotFrame
from sim.spaces import ActionSpace
from sim.vision import CameraSpec
from storage import keys

CAMS = (CameraSpec("front", 36, 32), CameraSpec("wrist", 36, 32))


def tiny_seeing_policy(cameras=CAMS) -> DiffusionPolicy:
    torch.manual_seed(0)
    p = DiffusionPolicy(
        DiffusionPolicyConfig(
            obs_dim=ROBOT_OBS.dim,
            network="mlp",
            mlp_hidden=16,
            step_embed_dim=8,
            num_inference_steps=2,
            obs_encoder_dims=(),
            cameras=cameras,
            image_channels=8,
            image_keypoints=4,
            image_features=8,
        )
    )
    rng = np.random.default_rng(0)
    p.fit_normalizers(rng.normal(size=(64, ROBOT_OBS.dim)), rng.uniform(size=(64, 10)))
    return p.eval()


def _images(b, h=1, seed=0, cameras=CAMS):
    g = torch.Generator().manual_seed(seed)
    return {c.name: torch.randint(0, 256, (b, h, c.size, c.size, 3), generator=g, dtype=torch.uint8) for c in cameras}


def test_spatial_softmax_finds_the_bright_spot():
    pool = SpatialSoftmax(1, 9, 9, 1)
    with torch.no_grad():
        pool.keypoints.weight.fill_(50.0)
        pool.keypoints.bias.zero_()
    x = torch.zeros(1, 1, 9, 9)
    x[0, 0, 2, 6] = 1.0  # row 2 (y), column 6 (x)
    xy = pool(x)[0].detach()
    np.testing.assert_allclose(xy.numpy(), [-1 + 2 * 6 / 8, -1 + 2 * 2 / 8], atol=1e-3)


def test_crops_are_centred_at_evaluation_and_random_in_training():
    frames = torch.arange(2 * 8 * 8 * 3, dtype=torch.int64).reshape(2, 8, 8, 3).to(torch.uint8)
    centre = crop_frames(frames, 6)
    assert centre.shape == (2, 3, 6, 6)
    torch.testing.assert_close(centre, frames.permute(0, 3, 1, 2)[:, :, 1:7, 1:7].float() / 255.0)
    crops = crop_frames(frames.repeat(16, 1, 1, 1), 6, torch.Generator().manual_seed(0))
    windows = {tuple(c[0, :, 0].numpy().round(6)) for c in crops}
    assert len(windows) > 1  # not all at one place
    for c, f in zip(crops, frames.repeat(16, 1, 1, 1), strict=True):  # each a window of its own frame
        full = f.permute(2, 0, 1).float() / 255.0
        assert any(torch.equal(c, full[:, i : i + 6, j : j + 6]) for i in range(3) for j in range(3)), (
            "a random crop is not a window of its frame"
        )


def test_the_seen_observation_is_the_state_then_each_cameras_features():
    p = tiny_seeing_policy()
    obs = torch.randn(3, 1, ROBOT_OBS.dim)
    seen = p.encode_observation(obs, _images(3))
    assert seen.shape == (3, 1, ROBOT_OBS.dim + 2 * 8) and p.seen_dim == seen.shape[-1]
    torch.testing.assert_close(seen[..., : ROBOT_OBS.dim], obs)
    other = p.encode_observation(obs, _images(3, seed=1))
    assert not torch.allclose(seen[..., ROBOT_OBS.dim :], other[..., ROBOT_OBS.dim :])  # the frames matter
    with pytest.raises(ValueError, match="encode_observation"):
        p.predict_action_chunk(obs)  # the state alone is not what it sees
    with pytest.raises(ValueError, match="no frames of \\['wrist'\\]"):
        p.encode_observation(obs, {"front": _images(3)["front"]})
    with pytest.raises(ValueError, match="pass their frames"):
        p.encode_observation(obs, None)


def test_training_sees_random_crops_and_learns():
    p = tiny_seeing_policy().train()
    b = 16
    batch = {keys.OBS: torch.randn(b, 1, ROBOT_OBS.dim), keys.ACTION: torch.rand(b, 1, 10)}
    batch |= {keys.image_key(n): v for n, v in _images(b).items()}
    opt = torch.optim.Adam(p.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    before = p.compute_loss(batch, torch.Generator().manual_seed(1)).item()
    for _ in range(60):
        loss = p.compute_loss(batch, g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    grads = [q.grad for q in p.image_encoder.parameters()]
    assert all(gr is not None for gr in grads) and any(float(gr.abs().sum()) > 0 for gr in grads)
    assert p.compute_loss(batch, torch.Generator().manual_seed(1)).item() < before


def test_a_config_with_cameras_round_trips_and_checks_them():
    cfg = tiny_seeing_policy().config
    d = cfg.to_dict()
    assert d["cameras"] == [c.to_json() for c in CAMS]
    assert DiffusionPolicyConfig.from_dict(d) == cfg
    assert "cameras" not in DiffusionPolicyConfig(obs_dim=4).to_dict()  # state-only configs read as before
    with pytest.raises(ValueError, match="named twice"):
        DiffusionPolicyConfig(obs_dim=4, cameras=(CAMS[0], CAMS[0]))
    with pytest.raises(ValueError, match="too small"):
        DiffusionPolicy(DiffusionPolicyConfig(obs_dim=4, cameras=(CameraSpec("front", 24, 20),)))
    with pytest.raises(ValueError, match="unknown camera"):
        DiffusionPolicyConfig(obs_dim=4, cameras=({"name": "top", "size": 24, "crop": 20},))


def _frame(rng, cameras=CAMS):
    pos = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.01, 3)
    hold = np.concatenate([pos, [1, 0, 0, 0, 1, 0], [-1.0]])
    images = {c.name: rng.integers(0, 256, (c.size, c.size, 3), dtype=np.uint8) for c in cameras}
    obs = np.concatenate([pos, [1, 0, 0, 0, 1, 0], [0.04, 0.04]]).astype(np.float32)
    return RobotFrame(obs, hold, pos, np.eye(3), np.array([0, 0, 0, 1.0]), 0.08, images=images, horizon=100)


def test_the_controller_encodes_each_robot_step_once_for_the_chunk_the_probe_and_every_signal():
    p = tiny_seeing_policy()
    calls = []
    forward = p.image_encoder.forward
    p.image_encoder.forward = lambda images, generator=None: (
        calls.append(len(next(iter(images.values())))) or forward(images, generator)
    )
    signals = {
        "denoising": make_signal("denoising", p, {"num_samples": 16}),
        "spread": make_signal("spread", p, {"num_samples": 8}),
    }
    space = ActionSpace(pos_low=(-0.5, -0.5, 0.7), pos_high=(0.5, 0.5, 1.3))
    ctl = Controller(p, signals, None, space)
    rng = np.random.default_rng(0)
    for rid in range(3):
        ctl.reset(rid, rid)
    for _ in range(4):
        steps = ctl.step({rid: _frame(rng) for rid in range(3)})
        assert all(np.isfinite(s.action).all() and set(s.scores) == set(signals) for s in steps.values())
        assert all(s.seen.shape == (1, p.seen_dim) for s in steps.values())
    assert calls == [3, 3, 3, 3]  # one batched call per tick, every robot once


def test_a_frame_without_the_policys_cameras_is_refused_clearly():
    p = tiny_seeing_policy()
    ctl = Controller(p, {}, None, ActionSpace(pos_low=(-0.5, -0.5, 0.7), pos_high=(0.5, 0.5, 1.3)))
    ctl.reset(0, 0)
    frame = _frame(np.random.default_rng(0), cameras=CAMS[:1])
    with pytest.raises(ValueError, match=r"camera\(s\) \['wrist'\].*images=True"):
        ctl.step({0: frame})


def test_the_novelty_box_of_a_seeing_policy_spans_its_cameras_features():
    from policy.signals.spread import demonstrations_range, novelty_against

    p = tiny_seeing_policy()
    with torch.no_grad():
        seen = p.encode_observation(torch.randn(32, 1, ROBOT_OBS.dim), _images(32))
        box = demonstrations_range(p, seen)
        assert len(box["low"]) == p.seen_dim
        inside = novelty_against(p, seen, box)
        shifted = seen.clone()
        shifted[..., ROBOT_OBS.dim :] += 10.0  # the same state, cameras that show something else
    assert float(inside.max()) == 0.0 and bool((novelty_against(p, shifted, box) > 0).all())

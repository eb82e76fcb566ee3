"""The object frame: turning the whole scene about the object changes nothing the network sees, and
an object-frame policy's world actions and noise field turn with the scene."""

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from policy.checkpoint import CheckpointError, load_policy, save_policy
from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.frames import ObjectFrame
from sim.demos import RECIPE_FILE, DemoRecipe
from sim.rotations import mat_to_rot6d
from sim.tasks.lift import LIFT_OBS, LIFT_WORKSPACE
from storage import keys
from tests.helpers import state_equal

SL = LIFT_OBS.slices()
FRAME = ObjectFrame.from_obs_spec(LIFT_OBS)


def _scene(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n lift observations (n, obs_dim) and actions (n, 10) with consistent geometry: object_to_eef_pos
    is object minus end effector, rotations are proper."""
    rng = np.random.default_rng(seed)
    obs = np.zeros((n, LIFT_OBS.dim))
    eef = rng.uniform([-0.1, -0.15, 0.85], [0.1, 0.15, 1.0], size=(n, 3))
    obj = np.concatenate([rng.uniform(-0.08, 0.08, size=(n, 2)), np.full((n, 1), 0.83)], axis=1)
    obs[:, SL["eef_pos"]] = eef
    obs[:, SL["eef_rot6d"]] = mat_to_rot6d(Rotation.random(n, random_state=seed).as_matrix())
    obs[:, SL["gripper_qpos"]] = rng.uniform(-0.04, 0.04, size=(n, 2))
    tilt = Rotation.from_euler("zx", np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.2, 0.2, n)], 1))
    obs[:, SL["object_pos"]] = obj
    obs[:, SL["object_rot6d"]] = mat_to_rot6d(tilt.as_matrix())
    obs[:, SL["object_to_eef_pos"]] = obj - eef
    obs[:, SL["object_extent"]] = rng.uniform(0.03, 0.1, size=(n, 3))
    act = np.zeros((n, 10))
    act[:, 0:3] = eef + rng.normal(0, 0.02, size=(n, 3))
    act[:, 3:9] = mat_to_rot6d(Rotation.random(n, random_state=seed + 1).as_matrix())
    act[:, 9] = rng.choice([-1.0, 1.0], n)
    return obs.astype(np.float32), act.astype(np.float32)


def _turned(obs: np.ndarray, act: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The same scenes turned by ``angle`` about the vertical through each object."""
    turn = Rotation.from_euler("z", angle)
    out, a = obs.copy(), act.copy()
    origin = obs[:, SL["object_pos"]]
    out[:, SL["eef_pos"]] = origin + turn.apply(obs[:, SL["eef_pos"]] - origin)
    out[:, SL["object_to_eef_pos"]] = turn.apply(obs[:, SL["object_to_eef_pos"]])
    for name in ("eef_rot6d", "object_rot6d"):
        r = obs[:, SL[name]]
        out[:, SL[name]] = np.concatenate([turn.apply(r[:, :3]), turn.apply(r[:, 3:])], axis=1)
    a[:, 0:3] = origin + turn.apply(act[:, 0:3] - origin)
    a[:, 3:9] = np.concatenate([turn.apply(act[:, 3:6]), turn.apply(act[:, 6:9])], axis=1)
    return out.astype(np.float32), a.astype(np.float32)


def test_frame_layout_comes_from_the_observation_spec():
    assert FRAME.object_pos == SL["object_pos"].start and FRAME.object_rot6d == SL["object_rot6d"].start
    assert FRAME.points == (SL["eef_pos"].start,) and FRAME.vectors == (SL["object_to_eef_pos"].start,)
    assert set(FRAME.rotations) == {SL["eef_rot6d"].start, SL["object_rot6d"].start}


def test_turning_the_scene_about_the_object_leaves_the_frame_observation_unchanged():
    obs, act = _scene(32)
    for angle in (0.3, -2.0, np.pi):
        t_obs, t_act = _turned(obs, act, angle)
        o, to = torch.as_tensor(obs)[:, None], torch.as_tensor(t_obs)[:, None]
        torch.testing.assert_close(FRAME.observation(to), FRAME.observation(o), atol=2e-6, rtol=0)
        a, ta = torch.as_tensor(act)[:, None], torch.as_tensor(t_act)[:, None]
        torch.testing.assert_close(FRAME.actions_to(ta, to), FRAME.actions_to(a, o), atol=2e-6, rtol=0)
    # in the frame the object's heading is gone: its x axis has no sideways component
    assert FRAME.observation(o)[..., SL["object_rot6d"].start + 1].abs().max() < 1e-6
    # a point at the object is the origin; the object's own position stays a world input
    framed = FRAME.observation(o)[:, 0]
    torch.testing.assert_close(framed[:, SL["object_pos"]], o[:, 0, SL["object_pos"]])


def test_actions_round_trip_and_noise_vectors_only_turn():
    obs, act = _scene(16)
    o, a = torch.as_tensor(obs)[:, None], torch.as_tensor(act)[:, None]
    torch.testing.assert_close(FRAME.actions_from(FRAME.actions_to(a, o), o), a, atol=1e-6, rtol=0)
    d = torch.randn_like(a)  # a difference of two actions: no translation, the norm is kept per part
    back = FRAME.actions_from(d, o, translate=False)
    torch.testing.assert_close(back[..., 0:3].norm(dim=-1), d[..., 0:3].norm(dim=-1))
    torch.testing.assert_close(back[..., 9], d[..., 9])


def test_heading_falls_back_to_zero_when_the_x_axis_is_vertical():
    obs, _ = _scene(1)
    obs[:, SL["object_rot6d"]] = mat_to_rot6d(Rotation.from_euler("y", -np.pi / 2).as_matrix())  # x up
    _, cos, sin = FRAME.pose(torch.as_tensor(obs))
    assert float(cos) == 1.0 and float(sin) == 0.0


@pytest.mark.parametrize(
    "bad",
    [
        {"object_pos": 11, "object_rot6d": 14, "points": [LIFT_OBS.dim - 2]},  # runs past the observation
        {"object_pos": 11, "object_rot6d": 14, "points": [0], "vectors": [1]},  # overlap
        {"object_pos": -1, "object_rot6d": 14},
        {"object_pos": 11, "object_rot6d": 14, "turns": [0]},  # unknown key
    ],
)
def test_bad_frame_layouts_are_refused(bad):
    with pytest.raises(ValueError, match="object.frame"):
        DiffusionPolicyConfig(obs_dim=LIFT_OBS.dim, object_frame=bad)


def test_frame_needs_the_object_pose_in_the_observation():
    from sim.env import ObsSpec

    with pytest.raises(ValueError, match="object_pos"):
        ObjectFrame.from_obs_spec(ObsSpec((("eef_pos", 3), ("object_rot6d", 6))))


def _frame_policy(obs: np.ndarray, act: np.ndarray) -> DiffusionPolicy:
    torch.manual_seed(0)
    cfg = DiffusionPolicyConfig(
        obs_dim=LIFT_OBS.dim,
        network="mlp",
        mlp_hidden=32,
        step_embed_dim=16,
        obs_encoder_dims=(32,),
        num_inference_steps=5,
        object_frame=FRAME,
    )
    policy = DiffusionPolicy(cfg)
    policy.fit_normalizers(obs, act, action_bounds=(LIFT_WORKSPACE.low, LIFT_WORKSPACE.high))
    return policy.eval()


def test_object_frame_policy_actions_turn_with_the_scene():
    """The same starting noise on a turned scene gives the turned action: the network sees the same."""
    obs, act = _scene(8)
    policy = _frame_policy(obs, act)
    t_obs, _ = _turned(obs, act, 1.1)
    noise = torch.randn((8, 1, 10), generator=torch.Generator().manual_seed(3))
    out = policy.predict_action_chunk(torch.as_tensor(obs)[:, None], noise=noise)[:, 0].numpy()
    t_out = policy.predict_action_chunk(torch.as_tensor(t_obs)[:, None], noise=noise)[:, 0].numpy()
    _, expected = _turned(obs, out, 1.1)
    np.testing.assert_allclose(t_out, expected, atol=2e-5)
    # callers keep world-frame actions: the action normalizer is the task's workspace
    np.testing.assert_allclose(policy.action_normalizer.stats()["min"][:3], LIFT_WORKSPACE.low[:3], atol=1e-6)


def test_object_frame_noise_field_turns_with_the_scene():
    """ε at k = 0 probed at world actions: the clean estimate a - span·ε (world units) turns with the scene."""
    obs, act = _scene(8)
    policy = _frame_policy(obs, act)
    t_obs, t_act = _turned(obs, act, -0.7)
    span = policy.action_normalizer.span

    @torch.no_grad()
    def estimate(o: np.ndarray, a: np.ndarray) -> np.ndarray:
        x = policy.normalize_action(torch.as_tensor(a))[:, None]
        eps = policy.noise_prediction(torch.as_tensor(o)[:, None], x, 0)[:, 0]
        return (torch.as_tensor(a) - 0.1 * eps * span).numpy()

    _, expected = _turned(obs, estimate(obs, act), -0.7)
    np.testing.assert_allclose(estimate(t_obs, t_act), expected, atol=2e-5)


def test_object_frame_training_and_checkpoint_round_trip(tmp_path):
    obs, act = _scene(64)
    policy = _frame_policy(obs, act).train()
    batch = {keys.OBS: torch.as_tensor(obs)[:, None], keys.ACTION: torch.as_tensor(act)[:, None]}
    loss = policy.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert torch.isfinite(loss) and all(p.grad is not None for p in policy.net.parameters())
    policy.eval()
    save_policy(policy, tmp_path / "p")
    loaded, doc = load_policy(tmp_path / "p")
    assert loaded.config.object_frame == FRAME and state_equal(policy, loaded)
    assert "frame_action" in doc["normalization"]
    # widening the observation range works on what the network sees (the frame), not on world values
    far = obs.copy()
    far[:, SL["object_extent"]] = 0.3
    assert loaded.widen_obs_range(far[:, None]) == 3
    doc["policy"]["object_frame"]["points"] = [LIFT_OBS.dim - 1]  # runs past the observation
    (tmp_path / "p" / "config.json").write_text(__import__("json").dumps(doc))
    with pytest.raises(CheckpointError, match="object frame"):
        load_policy(tmp_path / "p")


def test_train_command_trains_in_the_object_frame(tmp_path, capsys):
    from hitl.cli import main
    from storage.episodes import EpisodeWriter

    demos = tmp_path / "demos"
    for i in range(4):
        obs, act = _scene(12, seed=i)
        act[:, 0:3] = np.clip(act[:, 0:3], LIFT_WORKSPACE.low[:3], LIFT_WORKSPACE.high[:3])
        w = EpisodeWriter(demos / f"ep{i:02d}.mcap", {"task": "lift-cube", "seed": i}, object_names=[])
        for t in range(len(obs)):
            w.write_step(t, obs[t], act[t], act[t, :3], np.array([1.0, 0, 0, 0]), 0.04, t == 11, keys.SOURCE_EXPERT, {})
        w.finish(True, len(obs), "success")
    small = ["--steps", "3", "--batch-size", "8", "--network", "mlp", "--obs-encoder-dims", "16", "--quiet"]
    small += ["--data", str(demos), "--frame", "object"]
    out = tmp_path / "policy"
    assert main(["train", "--task", "lift-cube", "--out", str(out), *small]) == 0
    policy, doc = load_policy(out)
    assert policy.config.object_frame == FRAME and doc["policy"]["object_frame"]["object_pos"] == FRAME.object_pos
    assert doc["dataset"]["recipe"] is None  # these demos were not made by `hitl demos`: no way to re-record
    # demos that `hitl demos` made say how to record them again, and the policy keeps that recipe
    (demos / RECIPE_FILE).write_text(json.dumps(DemoRecipe("lift-cube", 4, seed=0).to_dict()))
    assert main(["train", "--task", "lift-cube", "--out", str(tmp_path / "again"), *small]) == 0
    assert load_policy(tmp_path / "again")[1]["dataset"]["recipe"] == DemoRecipe("lift-cube", 4).to_dict()
    capsys.readouterr()
    # a task whose observation has no object pose cannot train in its frame: a clear error, nothing written
    bad = tmp_path / "drawer"
    assert main(["train", "--task", "open-drawer", "--out", str(bad), *small]) == 2
    assert "object_pos" in capsys.readouterr().err and not bad.exists()


def test_a_shifted_object_moves_its_position_and_the_vectors_from_it_only():
    obs, _ = _scene(6)
    offset = np.random.default_rng(3).uniform(-0.04, 0.04, (6, 3)).astype(np.float32)
    hist = torch.as_tensor(np.stack([obs, obs], axis=1))  # (B, H=2, obs_dim): the same offset at both steps
    out = FRAME.shifted(hist, torch.as_tensor(offset)).numpy()
    moved = {"object_pos", "object_to_eef_pos"}
    for h in range(2):
        for name, sl in SL.items():
            expect = obs[:, sl] + (offset if name in moved else 0.0)
            assert np.allclose(out[:, h, sl], expect, atol=1e-6), name
    # in the frame of the shifted object, the end effector sits the offset away from where it sat
    framed = FRAME.observation(torch.as_tensor(out[:, :1]))[:, 0].numpy()
    plain = FRAME.observation(torch.as_tensor(obs[:, None]))[:, 0].numpy()
    assert not np.allclose(framed[:, SL["eef_pos"]], plain[:, SL["eef_pos"]], atol=1e-3)


def test_a_raised_end_effector_moves_with_its_targets_and_the_object_stays():
    obs, act = _scene(5)
    height = torch.as_tensor(np.linspace(-0.02, 0.02, 5))
    hist, chunk = torch.as_tensor(np.stack([obs, obs], axis=1)), torch.as_tensor(np.stack([act] * 3, axis=1))
    out, acts = FRAME.raised(hist, chunk, height)
    out, acts, dz = out.numpy(), acts.numpy(), height.numpy()[:, None]
    for h in range(2):
        assert np.allclose(out[:, h, SL["eef_pos"]][:, 2:], obs[:, SL["eef_pos"]][:, 2:] + dz)
        assert np.allclose(out[:, h, SL["object_to_eef_pos"]][:, 2:], obs[:, SL["object_to_eef_pos"]][:, 2:] - dz)
        rest = [
            c for n, sl in SL.items() for c in range(sl.start, sl.stop) if n not in ("eef_pos", "object_to_eef_pos")
        ]
        assert np.array_equal(out[:, h, rest], obs[:, rest])  # the object, the rays, the gripper: as they were
        assert np.array_equal(out[:, h, SL["eef_pos"]][:, :2], obs[:, SL["eef_pos"]][:, :2])
    assert np.allclose(acts[..., 2], act[:, None, 2] + dz) and np.array_equal(acts[..., 3:], chunk.numpy()[..., 3:])
    # in the object's frame, the end effector and its targets keep their relation
    assert np.allclose(acts[:, 0, 2] - out[:, 0, SL["eef_pos"]][:, 2], act[:, 2] - obs[:, SL["eef_pos"]][:, 2])


def test_origin_jitter_trains_an_object_frame_policy_only():
    from policy.train import TrainConfig, train_policy

    obs, act = _scene(64)
    data = {keys.OBS: obs[:, None], keys.ACTION: act[:, None]}
    for frame, ok in ((FRAME, True), (None, False)):
        cfg = DiffusionPolicyConfig(
            obs_dim=LIFT_OBS.dim, network="mlp", mlp_hidden=16, step_embed_dim=8, object_frame=frame
        )
        policy = DiffusionPolicy(cfg)
        policy.fit_normalizers(obs, act, action_bounds=(LIFT_WORKSPACE.low, LIFT_WORKSPACE.high))
        tcfg = TrainConfig(steps=3, batch_size=8, warmup_steps=1, origin_jitter=0.03, height_jitter=0.02)
        if ok:
            train_policy(policy, data, None, tcfg, progress=False)
        else:
            with pytest.raises(ValueError, match="object-frame"):
                train_policy(policy, data, None, tcfg, progress=False)
    with pytest.raises(ValueError, match="origin_jitter"):
        TrainConfig(origin_jitter=-0.01)
    with pytest.raises(ValueError, match="height_jitter"):
        TrainConfig(height_jitter=True)

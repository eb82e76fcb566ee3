import numpy as np
import pytest
import torch

from policy.calibrate import CalibrationError, calibrate
from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.uncertainty import UncertaintyConfig
from storage import keys
from storage.dataset import DatasetConfig, load_dataset
from storage.episodes import EpisodeWriter

OBS_DIM = 5


QUAT = np.array([1.0, 0, 0, 0])


def _episodes(folder, lengths, written=None):
    """Episodes of ``lengths`` steps; ``written`` (a dict) gets, per file name, what each step wrote: the
    observation, the end-effector position and the gripper command in force (the previous action's, open
    at the first step)."""
    rng = np.random.default_rng(0)
    for i, n in enumerate(lengths):
        name = f"ep{i:02d}.mcap"
        w = EpisodeWriter(folder / name, {"task": "unit", "seed": i}, object_names=[])
        steps = []
        for t in range(n):
            act = np.r_[rng.uniform(-0.1, 0.1, 3), [0, 1, 0, -1, 0, 0], [1.0 if t > 2 else -1.0]]
            obs = rng.normal(size=OBS_DIM)
            w.write_step(t, obs, act, act[:3], QUAT, 0.04, t == n - 1, keys.SOURCE_EXPERT, {})
            steps.append((obs, act[:3], 1.0 if t > 3 else -1.0))  # action t-1's gripper: closed from t = 3 on
        w.finish(True, n, "success")
        if written is not None:
            written[name] = steps
    return folder


def _u_of_steps(policy, steps, cfg, batch=64):
    """U at each step, scored here from what the episodes wrote: the observation, and a probe centred on
    the end effector's pose with the gripper command in force; in batches of ``batch`` steps, in order
    (the estimator's probe depends on its seed and call order)."""
    from policy.uncertainty import UncertaintyEstimator
    from sim.rotations import quat_to_rot6d

    rot = quat_to_rot6d(QUAT)
    estimator, out = UncertaintyEstimator(cfg), []
    for i in range(0, len(steps), batch):
        part = steps[i : i + batch]
        obs = torch.tensor(np.stack([o for o, _, _ in part]), dtype=torch.float32)[:, None]  # obs_horizon 1
        center = torch.tensor(np.stack([np.r_[pos, rot, g] for _, pos, g in part]), dtype=torch.float32)
        out.append(estimator(policy.noise_prediction, obs, policy.normalize_action(center)).U.numpy())
    return np.concatenate(out)


def _policy(folder):
    ds = load_dataset(folder, DatasetConfig())
    torch.manual_seed(0)
    p = DiffusionPolicy(
        DiffusionPolicyConfig(obs_dim=OBS_DIM, network="mlp", mlp_hidden=32, step_embed_dim=8, obs_encoder_dims=(16,))
    )
    p.fit_normalizers(ds.obs, ds.actions)
    p.eval()
    train, val = ds.split()
    info = {"dataset": {"train_episodes": [ds.names[i] for i in train], "val_episodes": [ds.names[i] for i in val]}}
    return p, info, ds


def test_calibration_uses_only_the_validation_episodes(tmp_path):
    written = {}
    folder = _episodes(tmp_path / "demos", [7, 9, 11, 13, 15, 17, 19, 21, 23, 25], written)
    policy, info, ds = _policy(folder)
    cfg = UncertaintyConfig(num_samples=32)
    rec = calibrate(policy, info, folder, 0.95, cfg, progress=False)
    val, train = info["dataset"]["val_episodes"], info["dataset"]["train_episodes"]
    assert list(rec.episodes) == val and not set(val) & set(train)
    assert rec.samples == sum(len(written[n]) for n in val)
    # the threshold is the quantile of U over the validation steps, scored here from what they wrote
    u = _u_of_steps(policy, [step for n in val for step in written[n]], cfg)
    assert rec.threshold == pytest.approx(float(np.quantile(u, 0.95)), rel=1e-6)
    assert rec.validation_share_above == pytest.approx(float(np.mean(u > np.quantile(u, 0.95))))
    assert (rec.u_mean, rec.u_median, rec.u_max) == pytest.approx((u.mean(), np.median(u), u.max()), rel=1e-6)
    # the training steps scored instead give another threshold: they are not mixed in
    u_train = _u_of_steps(policy, [step for n in train for step in written[n]], cfg)
    assert float(np.quantile(u_train, 0.95)) != pytest.approx(rec.threshold, rel=1e-3)
    assert rec.uncertainty == cfg
    # the record calibration.json keeps, in its order
    record = rec.to_dict()
    assert list(record) == [
        "threshold",
        "quantile",
        "validation_share_above",
        "samples",
        "episodes",
        "episodes_checked",
        "data",
        "uncertainty",
        "u_stats",
    ]
    assert record["episodes"] == val and record["uncertainty"] == cfg.to_dict()
    assert record["u_stats"] == {"mean": rec.u_mean, "median": rec.u_median, "max": rec.u_max}
    assert record["episodes_checked"] == {"identical": 0, "by_recipe": 0, "unverified": len(val)}
    # the training episodes scored instead give the other steps: none of them is mixed in
    swapped = {"dataset": {"train_episodes": val, "val_episodes": train}}
    assert calibrate(policy, swapped, folder, 0.95, cfg, progress=False).samples + rec.samples == len(ds.obs)


def test_calibration_refuses_unsafe_inputs(tmp_path):
    folder = _episodes(tmp_path / "demos", [5, 6, 7])
    policy, info, _ = _policy(folder)
    leaked = {"dataset": {"train_episodes": ["ep00.mcap", "ep01.mcap"], "val_episodes": ["ep01.mcap"]}}
    with pytest.raises(CalibrationError, match="both training and validation"):
        calibrate(policy, leaked, folder, progress=False)
    with pytest.raises(CalibrationError, match="none of the policy"):
        calibrate(policy, {"dataset": {"val_episodes": ["other.mcap"]}}, folder, progress=False)
    # episodes whose steps are not the held-out ones (and no recipe recorded them) are refused
    digests = {
        "dataset": {**info["dataset"], "val_episode_digest": {n: "sha256:0" for n in info["dataset"]["val_episodes"]}}
    }
    with pytest.raises(CalibrationError, match="its steps differ from the ones the policy held out"):
        calibrate(policy, digests, folder, progress=False)
    # file sizes are no evidence (the same steps recorded twice differ in size): an older record is not read
    sizes = {"dataset": {**info["dataset"], "val_episode_bytes": {n: 1 for n in info["dataset"]["val_episodes"]}}}
    assert calibrate(policy, sizes, folder, config=UncertaintyConfig(num_samples=8), progress=False).samples > 0
    with pytest.raises(ValueError, match="quantile"):
        calibrate(policy, info, folder, quantile=1.5, progress=False)


def test_validation_share_is_the_quantiles_complement(tmp_path):
    folder = _episodes(tmp_path / "demos", [20, 22, 24, 26, 28, 30, 32, 34, 36, 38])
    policy, info, _ = _policy(folder)
    rec = calibrate(policy, info, folder, 0.9, UncertaintyConfig(num_samples=32), progress=False)
    assert abs(rec.validation_share_above - 0.1) <= 1.5 / rec.samples + 1e-9


def test_rollout_check_measures_the_share_above_on_autonomous_rollouts():
    """On the policy's own rollouts through the one controller: every step scored, the share above the
    threshold counted, and a share over FLAG_SHARE flagged."""
    from policy.calibrate import FLAG_SHARE
    from policy.evaluate import rollout_check
    from tests.helpers import tiny_policy

    policy = tiny_policy("lift-cube")
    cfg = UncertaintyConfig(num_samples=16)
    low = rollout_check(policy, "lift-cube", 0.0, cfg, episodes=1, seed=3000, progress=False)
    assert low["steps"] == 150 and low["episodes"] == 1 and low["seeds"] == [3000, 3000]
    assert low["share_above"] > FLAG_SHARE and low["flagged"]
    # the same seed replays the same U: a threshold at its median puts about half the steps above
    mid = rollout_check(policy, "lift-cube", low["u_median"], cfg, episodes=1, seed=3000, progress=False)
    assert mid["u_median"] == pytest.approx(low["u_median"])
    assert 0.4 <= mid["share_above"] <= 0.5 and mid["flagged"]
    high = rollout_check(policy, "lift-cube", float("inf"), cfg, episodes=1, seed=3000, progress=False)
    assert high["share_above"] == 0.0 and not high["flagged"]
    with pytest.raises(ValueError, match="episodes"):
        rollout_check(policy, "lift-cube", 0.0, cfg, episodes=0, progress=False)

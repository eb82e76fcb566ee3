"""Uncertainty threshold = a quantile of U over the held-out validation episodes.

The validation episodes are the ones ``hitl train`` held out (their names are in
the policy's config.json), so calibration never sees a training episode. The
current end-effector pose of each recorded step is the probe's centre; the
gripper dimension holds the command in force at that step (the previous
action's gripper, open at the first step), as in live rollouts. The folder's
episodes must be the held-out ones, by their content or by the recipe that
recorded them (``policy.heldout``).

By construction 1 - quantile of the validation steps lie above the threshold.
``policy.evaluate.rollout_check`` measures the same share on the policy's own autonomous
rollouts of its training task, which is what the fleet sees: a share far above
the validation one (``FLAG_SHARE``) means the validation states do not look
like the states the policy visits, and the robots would flood the queue.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from policy.heldout import HeldOutCheck, HeldOutError, check_held_out
from policy.uncertainty import UncertaintyConfig, UncertaintyEstimator
from sim.rotations import quat_to_rot6d
from storage import keys
from storage.dataset import DatasetConfig, DemoDataset, load_dataset
from storage.paths import portable

FLAG_SHARE = 0.15  # a rollout share above the threshold over this is a calibration problem


class CalibrationError(ValueError):
    pass


@dataclass(frozen=True)
class Calibration:
    """The denoising threshold and its evidence (``to_dict``: the record of calibration.json).

    threshold: the ``quantile`` of U over the ``samples`` steps of the validation ``episodes`` (names),
    ``validation_share_above`` of them above it; episodes_checked: how they were found to be the held-out
    ones; data: the folder (``storage.paths.portable``); uncertainty: the estimator's settings;
    u_mean, u_median, u_max: U over those steps.
    """

    threshold: float
    quantile: float
    validation_share_above: float
    samples: int
    episodes: tuple[str, ...]
    episodes_checked: HeldOutCheck
    data: str
    uncertainty: UncertaintyConfig
    u_mean: float
    u_median: float
    u_max: float

    def to_dict(self) -> dict:
        return {
            "threshold": self.threshold,
            "quantile": self.quantile,
            "validation_share_above": self.validation_share_above,
            "samples": self.samples,
            "episodes": list(self.episodes),
            "episodes_checked": self.episodes_checked.to_dict(),
            "data": self.data,
            "uncertainty": self.uncertainty.to_dict(),
            "u_stats": {"mean": self.u_mean, "median": self.u_median, "max": self.u_max},
        }


def current_actions(ds: DemoDataset, rows: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(M, 10) raw actions holding the recorded end-effector pose and gripper command at ``rows``."""
    pose = ds.ee_pose[rows]
    rot = np.stack([quat_to_rot6d(q) for q in pose[:, 3:7]])
    prev = np.where(rows > starts, rows - 1, rows)
    gripper = np.where(rows > starts, ds.actions[prev, 9], -1.0)
    return np.concatenate([pose[:, 0:3], rot, gripper[:, None]], axis=1).astype(np.float32)


@torch.no_grad()
def seen_windows(policy: DiffusionPolicy, ds: DemoDataset, index: np.ndarray, batch: int = 256) -> np.ndarray:
    """(M, H, seen_dim) float32: what the policy sees at the sample rows ``index`` of ``ds``
    (``DemoDataset.sample_index``): the state histories, and for a policy that sees cameras what its
    encoders make of their frames (``DiffusionPolicy.encode_observation``, centred crops), encoded once."""
    obs, _ = ds.windows(index)
    obs = obs.astype(np.float32)
    cameras = [c.name for c in policy.config.cameras]
    if not cameras:
        return obs
    if lacks := [c for c in cameras if c not in ds.images]:
        raise CalibrationError(f"{ds.folder} holds no frames of camera(s) {lacks} the policy sees")
    out = []
    for i in range(0, len(index), batch):
        frames = ds.image_windows(index[i : i + batch])
        images = {c: torch.as_tensor(frames[keys.image_key(c)]) for c in cameras}
        out.append(policy.encode_observation(torch.as_tensor(obs[i : i + batch]), images).numpy())
    return np.concatenate(out) if out else np.zeros((0, obs.shape[1], policy.seen_dim), np.float32)


def _validation_episodes(
    policy: DiffusionPolicy, data: str | Path, val_episodes: list[str]
) -> tuple[DemoDataset, np.ndarray]:
    cfg = policy.config
    ds = load_dataset(data, DatasetConfig(obs_horizon=cfg.obs_horizon, action_horizon=cfg.action_horizon))
    wanted = set(val_episodes)
    episodes = np.array([i for i, name in enumerate(ds.names) if name in wanted], dtype=np.int64)
    if len(episodes) == 0:
        raise CalibrationError(
            f"none of the policy's {len(wanted)} validation episodes is in {data}; calibrate on the folder the "
            "policy was trained from (validation episodes are never used for training)"
        )
    return ds, episodes


def _uncertainty(
    policy: DiffusionPolicy,
    ds: DemoDataset,
    episodes: np.ndarray,
    config: UncertaintyConfig,
    batch: int,
    progress: bool,
) -> tuple[np.ndarray, list[str]]:
    cfg = policy.config
    index = ds.sample_index(episodes)
    obs = seen_windows(policy, ds, index)
    centers = current_actions(ds, index[:, 0], index[:, 1])
    estimator = UncertaintyEstimator(config)
    values = []
    bar = tqdm(total=len(index), desc="calibrate", disable=not progress, unit="step")
    try:
        for i in range(0, len(index), batch):
            o = torch.as_tensor(obs[i : i + batch])
            c = policy.normalize_action(torch.as_tensor(centers[i : i + batch]))
            values.append(estimator(policy.noise_prediction, o, c, chunk=cfg.action_horizon).U.numpy())
            bar.update(len(o))
    finally:
        bar.close()
    return np.concatenate(values), [ds.names[i] for i in episodes]


def calibrate(
    policy: DiffusionPolicy,
    info: dict,
    data: str | Path,
    quantile: float = 0.95,
    config: UncertaintyConfig | None = None,
    progress: bool = True,
) -> Calibration:
    """The threshold at ``quantile`` of U over the policy's held-out validation episodes in ``data``."""
    if not 0 < quantile < 1:
        raise ValueError(f"quantile must be in (0, 1), got {quantile!r}")
    config = config or UncertaintyConfig()
    val = info.get("dataset", {}).get("val_episodes")
    train = set(info.get("dataset", {}).get("train_episodes", []))
    if not val:
        raise CalibrationError("the policy's config.json lists no validation episodes (train with val_fraction > 0)")
    if train & set(val):
        raise CalibrationError(f"episodes listed as both training and validation: {sorted(train & set(val))[:5]}")
    ds, episodes = _validation_episodes(policy, data, val)
    try:  # by content, or by the recipe that recorded them (policy.heldout)
        held_out = check_held_out(ds, list(episodes), info)
    except HeldOutError as exc:
        raise CalibrationError(str(exc)) from None
    u, used = _uncertainty(policy, ds, episodes, config, 64, progress)
    threshold = float(np.quantile(u, quantile))
    return Calibration(
        threshold=threshold,
        quantile=quantile,
        validation_share_above=float(np.mean(u > threshold)),
        samples=int(len(u)),
        episodes=tuple(used),
        episodes_checked=held_out,
        data=portable(data),
        uncertainty=config,
        u_mean=float(u.mean()),
        u_median=float(np.median(u)),
        u_max=float(u.max()),
    )

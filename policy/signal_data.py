"""Calibration and training data for the signals: the policy's demonstration split and its own
rollouts (cached next to the policy, keyed by the weights they came from)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from policy.calibrate import CalibrationError, current_actions, seen_windows
from policy.checkpoint import WEIGHTS
from policy.diffusion_policy import DiffusionPolicy
from policy.evaluate import PolicyEpisode, rollout_policy
from policy.signals.base import CalibrationData, StepSet
from storage.dataset import DatasetConfig, DemoDataset, load_dataset

ROLLOUT_DIR = "rollouts"


def _demo_steps(policy: DiffusionPolicy, ds: DemoDataset, episodes: np.ndarray) -> StepSet:
    """The steps of ``episodes``, observed as the policy sees them (``seen_windows``)."""
    index = ds.sample_index(episodes)
    _, act = ds.windows(index)
    obs = seen_windows(policy, ds, index)
    starts = ds.episode_starts
    ep_of_row = np.searchsorted(ds.episode_ends, index[:, 0], side="right")
    return StepSet(
        obs=obs.astype(np.float32),
        action=act.astype(np.float32),
        current=current_actions(ds, index[:, 0], index[:, 1]),
        episode=ep_of_row.astype(np.int64),
        t=(index[:, 0] - starts[ep_of_row]).astype(np.int64),
        last=(index[:, 2] - 1 - index[:, 1]).astype(np.int64),
        success=np.ones(len(index), dtype=bool),  # datasets keep successful demonstrations
        names=list(ds.names),
    )


def demo_data(policy: DiffusionPolicy, info: dict, folder: str | Path) -> CalibrationData:
    """The training and validation demonstrations exactly as the policy's config.json split them."""
    cfg = policy.config
    ds = load_dataset(folder, DatasetConfig(obs_horizon=cfg.obs_horizon, action_horizon=cfg.action_horizon))
    split = info.get("dataset", {})
    train_names, val_names = set(split.get("train_episodes", [])), set(split.get("val_episodes", []))
    if not val_names:
        raise CalibrationError("the policy's config.json lists no validation episodes (train with val_fraction > 0)")
    train = np.array([i for i, n in enumerate(ds.names) if n in train_names], dtype=np.int64)
    val = np.array([i for i, n in enumerate(ds.names) if n in val_names], dtype=np.int64)
    if len(train) == 0 or len(val) == 0:
        raise CalibrationError(
            f"{folder} holds {len(train)} of the policy's training and {len(val)} of its validation episodes: "
            "use the folder the policy was trained from"
        )
    return CalibrationData(train=_demo_steps(policy, ds, train), val=_demo_steps(policy, ds, val))


def episodes_to_steps(episodes: list[PolicyEpisode]) -> StepSet:
    """Traced rollouts (``rollout_policy(..., trace=True)``) as a StepSet; action is (M, 1, 10) executed."""
    cols: dict[str, list] = {k: [] for k in ("obs", "action", "current", "episode", "t", "last", "success")}
    for e, ep in enumerate(episodes):
        if not ep.trace:
            raise ValueError(f"episode {ep.task}/{ep.seed} has no trace: roll out with trace=True")
        n = len(ep.trace)
        cols["obs"].append(np.stack([s[0] for s in ep.trace]))
        cols["current"].append(np.stack([s[1] for s in ep.trace]))
        cols["action"].append(np.stack([s[2] for s in ep.trace])[:, None])
        cols["episode"].append(np.full(n, e))
        cols["t"].append(np.arange(n))
        cols["last"].append(np.full(n, n - 1))
        cols["success"].append(np.full(n, ep.success))
    return StepSet(
        obs=np.concatenate(cols["obs"]).astype(np.float32),
        action=np.concatenate(cols["action"]).astype(np.float32),
        current=np.concatenate(cols["current"]).astype(np.float32),
        episode=np.concatenate(cols["episode"]).astype(np.int64),
        t=np.concatenate(cols["t"]).astype(np.int64),
        last=np.concatenate(cols["last"]).astype(np.int64),
        success=np.concatenate(cols["success"]).astype(bool),
        names=[f"{ep.task}/seed{ep.seed}" for ep in episodes],
    )


def _weights_key(policy_dir: Path) -> str:
    st = (policy_dir / WEIGHTS).stat()
    return hashlib.sha256(f"{st.st_size}:{st.st_mtime_ns}".encode()).hexdigest()[:12]


def policy_rollouts(
    policy: DiffusionPolicy,
    policy_dir: str | Path,
    task: str,
    seeds: list[int],
    n_envs: int = 8,
    progress: bool = True,
) -> StepSet:
    """The policy's own autonomous rollouts on ``task``; cached under ``<policy>/rollouts/``."""
    policy_dir = Path(policy_dir)
    key = f"{task}-{seeds[0]}-{len(seeds)}-{_weights_key(policy_dir)}.npz"
    path = policy_dir / ROLLOUT_DIR / key
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                return StepSet(**{k: z[k] for k in z.files if k != "names"}, names=json.loads(str(z["names"])))
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)  # a damaged cache is rolled out again
    episodes, _ = rollout_policy(policy, task, seeds, n_envs=n_envs, progress=progress, trace=True)
    steps = episodes_to_steps(episodes)
    path.parent.mkdir(exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(
        tmp,
        names=np.array(json.dumps(steps.names)),
        **{k: getattr(steps, k) for k in ("obs", "action", "current", "episode", "t", "last", "success")},
    )
    tmp.replace(path)
    return steps

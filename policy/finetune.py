"""Fine-tuning a policy version on takeover data: the training, the recalibration, the evaluation and
the promotion gate. No database here: ``server.finetune.job`` runs these steps as a job and records
them in the registry.

Training starts from the parent's weights and its action normalizer (its absolute action space).
The observation normalizer keeps the parent's range and is widened to cover the takeover
observations (``widen_obs_range``): a state on an object the parent never saw (a hammer's extent
after a cube's) would otherwise reach the network several ranges outside anything it was trained
on, and small takeover sets taught it nothing (docs/benchmarks/finetune.md, "finetune-widened"). Every
mini-batch mixes ``ratio`` takeover / ``1 - ratio`` pretraining (``policy.mixing``), and the number
of steps grows with the takeover data (``FinetuneConfig.steps_for``).
Evaluation rolls the policy out autonomously through the one ``Controller`` (``rollout_policy``) on
seeded episodes of the lineage's tasks.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from policy.diffusion_policy import DiffusionPolicy
from policy.heldout import HeldOutError, check_held_out
from policy.mixing import MixedSampler
from policy.train import TrainConfig, TrainState, train_policy
from storage import keys
from storage.dataset import DatasetConfig, load_dataset
from storage.obs_layout import describe, mismatched, recorded
from storage.takeovers import TakeoverSelection


@dataclass(frozen=True)
class FinetuneConfig:
    """ratio: takeover share of each mini-batch; steps: ``passes`` expected visits of each takeover
    sample (``passes * N / (ratio * batch_size)``) clipped to [min_steps, max_steps], or ``steps`` when
    given; tolerance: how much training-task success may drop; min_gain: how much the target tasks'
    mean success must rise (strictly more than this); widen_obs_range: widen the child's observation
    normalizer to cover the takeover observations (False: keep the parent's, as before);
    successful_only, takeover_tail: which takeovers and steps to learn from
    (``storage.takeovers.TakeoverSelection``: only takeovers of successful episodes; of each, only its
    last ``takeover_tail`` steps); fit_episodes, fit_seed: the candidate's own episodes per task on which
    its asking signal's thresholds are fitted (``fit_threshold_on_own_episodes``), on seeds apart from the
    gate's."""

    ratio: float = 0.5
    batch_size: int = 64
    lr: float = 5e-4
    warmup_steps: int = 20
    passes: float = 60.0
    min_steps: int = 500
    max_steps: int = 6000
    steps: int | None = None
    seed: int = 0
    checkpoint_every: int = 100
    quantile: float = 0.95
    eval_episodes: int = 20
    eval_seed: int = 50_000
    tolerance: float = 0.05
    min_gain: float = 0.0
    widen_obs_range: bool = True
    successful_only: bool = False
    takeover_tail: int | None = None
    fit_episodes: int = 20
    fit_seed: int = 60_000

    def __post_init__(self) -> None:
        self.selection  # noqa: B018 - validates takeover_tail
        if not 0 < self.ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio!r}")
        for name in ("batch_size", "min_steps", "max_steps", "checkpoint_every", "eval_episodes", "fit_episodes"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if self.steps is not None and not (isinstance(self.steps, int) and self.steps >= 1):
            raise ValueError(f"steps must be an integer >= 1, got {self.steps!r}")
        if not (isinstance(self.fit_seed, int) and self.fit_seed >= 0):
            raise ValueError(f"fit_seed must be an integer >= 0, got {self.fit_seed!r}")
        fit = range(self.fit_seed, self.fit_seed + self.fit_episodes)
        judged = range(self.eval_seed, self.eval_seed + self.eval_episodes)
        if fit.start < judged.stop and judged.start < fit.stop:
            raise ValueError(
                f"the threshold-fitting seeds {fit.start}..{fit.stop - 1} overlap the gate's "
                f"{judged.start}..{judged.stop - 1}: the gate must judge on episodes that chose no setting"
            )
        if self.min_steps > self.max_steps:
            raise ValueError(f"min_steps {self.min_steps} > max_steps {self.max_steps}")
        if not (self.passes > 0 and math.isfinite(self.passes)):
            raise ValueError(f"passes must be a positive number, got {self.passes!r}")
        if not 0 <= self.tolerance < 1:
            raise ValueError(f"tolerance must be in [0, 1), got {self.tolerance!r}")
        if not 0 < self.quantile < 1:
            raise ValueError(f"quantile must be in (0, 1), got {self.quantile!r}")

    def steps_for(self, takeover_samples: int) -> int:
        if self.steps is not None:
            return self.steps
        wanted = math.ceil(self.passes * takeover_samples / (self.ratio * self.batch_size))
        return int(min(self.max_steps, max(self.min_steps, wanted)))

    def train_config(self, takeover_samples: int) -> TrainConfig:
        steps = self.steps_for(takeover_samples)
        return TrainConfig(
            steps=steps,
            batch_size=self.batch_size,
            lr=self.lr,
            warmup_steps=min(self.warmup_steps, steps - 1),
            seed=self.seed,
            val_every=max(steps, 1),
        )

    @property
    def selection(self) -> TakeoverSelection:
        return TakeoverSelection(successful_only=bool(self.successful_only), tail=self.takeover_tail)

    def to_dict(self) -> dict:
        return asdict(self)


class FinetuneDataError(ValueError):
    """The data for a fine-tuning run is missing or unusable; the message says what and where."""


def check_layout(files: Iterable[tuple[str, dict]], info: dict, where: str | Path) -> None:
    """Raises FinetuneDataError naming the episode files of ``where`` ((name, metadata) pairs) recorded
    with another observation layout than the one the policy (its config.json ``info``) was trained on,
    and the channels that differ. Files that record no layout, and a policy that records none, are left
    to the size checks."""
    labels = recorded(info)
    other = mismatched(files, labels) if labels is not None else {}
    if other:
        shown = "; ".join(f"{name}: {why}" for name, why in list(other.items())[:3])
        more = f"; and {len(other) - 3} more" if len(other) > 3 else ""
        raise FinetuneDataError(
            f"{len(other)} episode(s) of {where} were recorded with another observation layout than the policy's "
            f"{describe(labels)}: {shown}{more}"
        )


MAX_LEFT_OUT = 0.05  # the share of named pretraining episodes a re-recording may lose (see pretraining_split)


@dataclass(frozen=True)
class PretrainingSplit:
    """The pretraining set split exactly as the policy's config.json records it: train / val
    ({OBS: (M, H, obs_dim), ACTION: (M, C, 10)}), the training episodes' names, the named episodes left
    out (name: why) and how the episodes were identified (``policy.heldout.HeldOutCheck.to_dict``)."""

    train: dict[str, np.ndarray]
    val: dict[str, np.ndarray]
    train_names: list[str]
    left_out: dict[str, str]
    checked: dict[str, int]


def pretraining_split(policy: DiffusionPolicy, info: dict, folder: str | Path) -> PretrainingSplit:
    """The policy's pretraining episodes in ``folder``, identified as ``policy.heldout`` does.

    A folder recorded again from the policy's recipe (the fine-tuning job does, on a machine without
    the data) may hold an episode whose scripted expert failed there although it succeeded where the
    policy was trained: the dataset leaves unsuccessful episodes out, and so does the split, naming
    them in ``left_out``. More than ``MAX_LEFT_OUT`` of the named episodes missing, or
    any named episode missing for another reason, means the folder is not the policy's: refused."""
    folder = Path(folder)
    split = info.get("dataset", {})
    train_names, val_names = split.get("train_episodes") or [], split.get("val_episodes") or []
    if not train_names:
        raise FinetuneDataError("the policy's config.json lists no training episodes: which data pretrained it?")
    if not folder.is_dir():
        raise FinetuneDataError(
            f"pretraining data {folder} not found (named in the policy's config.json, which holds no recipe to "
            "record it again): record it with `hitl demos` as it was recorded, or pass --pretrain-data"
        )
    cfg = policy.config
    ds = load_dataset(folder, DatasetConfig(obs_horizon=cfg.obs_horizon, action_horizon=cfg.action_horizon))
    index = {n: i for i, n in enumerate(ds.names)}
    named = [*train_names, *val_names]
    missing = [n for n in named if n not in index]
    has_recipe = split.get("recipe") is not None
    left_out = {
        n: "unsuccessful when recorded again" for n in missing if has_recipe and ds.excluded.get(n) == "unsuccessful"
    }
    lost = [n for n in missing if n not in left_out]
    if lost or len(left_out) > MAX_LEFT_OUT * len(named):
        example = (lost or missing)[0]
        raise FinetuneDataError(
            f"{len(missing)} of the policy's {len(named)} pretraining episodes are not in {folder}'s dataset (e.g. "
            f"{example}: {ds.excluded.get(example, 'no such file')}): is this the folder it was trained from?"
        )
    check_layout([(n, ds.meta[index[n]]) for n in named if n in index], info, folder)
    if ds.obs.shape[1] != cfg.obs_dim:
        raise FinetuneDataError(f"{folder} holds {ds.obs.shape[1]}-dim observations, the policy takes {cfg.obs_dim}")
    train_names = [n for n in train_names if n in index]
    train_ids = np.array([index[n] for n in train_names], np.int64)
    val_ids = np.array([index[n] for n in val_names if n in index], np.int64)
    try:
        checked = check_held_out(ds, [*train_ids.tolist(), *val_ids.tolist()], info)
    except HeldOutError as exc:
        raise FinetuneDataError(str(exc)) from None
    train_index, val_index = ds.sample_index(train_ids), ds.sample_index(val_ids)
    train = dict(zip((keys.OBS, keys.ACTION), ds.windows(train_index), strict=True)) | ds.image_windows(train_index)
    val = dict(zip((keys.OBS, keys.ACTION), ds.windows(val_index), strict=True)) | ds.image_windows(val_index)
    return PretrainingSplit(train, val, train_names, left_out, checked.to_dict())


def finetune_policy(
    parent: DiffusionPolicy,
    takeover: dict[str, np.ndarray],
    pretrain: dict[str, np.ndarray],
    cfg: FinetuneConfig,
    work_dir: str | Path | None = None,
    progress: bool = True,
    on_checkpoint: Callable[[TrainState], None] | None = None,
) -> tuple[DiffusionPolicy, dict]:
    """Trains a copy of ``parent`` (its weights and normalizers) on ``takeover`` mixed with ``pretrain``
    ({OBS: (M, H, obs_dim), ACTION: (M, C, 10)}, absolute actions). With ``work_dir``, a training state is
    saved there every ``checkpoint_every`` steps (after ``on_checkpoint``, which may raise to stop the
    run first) and an existing one is resumed. Returns (EMA policy, history)."""
    n_take = len(takeover[keys.OBS])
    if n_take == 0:
        raise FinetuneDataError("no takeover samples to fine-tune on")
    n_pre = len(pretrain[keys.OBS]) if cfg.ratio < 1 else 0
    wanted = (keys.OBS, keys.ACTION, *(keys.image_key(c.name) for c in parent.config.cameras))
    if lacks := [k for k in wanted if k not in takeover or (n_pre and k not in pretrain)]:
        raise FinetuneDataError(f"the policy sees {list(wanted[2:])}: no {lacks} in the fine-tuning data")
    data = {k: np.concatenate([takeover[k], pretrain[k][: n_pre or 0]]) for k in wanted}
    sampler = MixedSampler(n_take, n_pre, cfg.ratio)
    policy = copy.deepcopy(parent)
    widened = policy.widen_obs_range(takeover[keys.OBS]) if cfg.widen_obs_range else 0
    tcfg = cfg.train_config(n_take)
    resume = TrainState.load(work_dir) if work_dir is not None and TrainState.exists(work_dir) else None

    def checkpoint(state: TrainState) -> None:
        if on_checkpoint is not None:  # first: a job that lost its lease must not overwrite the state
            on_checkpoint(state)
        if work_dir is not None:
            state.save(work_dir)

    ema, history = train_policy(
        policy,
        data,
        None,
        tcfg,
        progress=progress,
        sampler=sampler,
        resume=resume,
        checkpoint=checkpoint,
        checkpoint_every=cfg.checkpoint_every,
    )
    history |= {
        "steps": tcfg.steps,
        "takeover_samples": n_take,
        "pretraining_samples": n_pre,
        "ratio": cfg.ratio,
        "obs_dims_widened": widened,
        "resumed_from_step": resume.step if resume is not None else None,
    }
    return ema, history


MIN_FIT_SUCCESSES = 10  # fewer of the candidate's own successful episodes fit nothing


def fit_threshold_on_own_episodes(
    policy: DiffusionPolicy,
    signal,
    name: str,
    tasks: list[str],
    scene: str,
    episodes: int,
    seed: int,
    progress: bool = True,
) -> dict:
    """Raises ``signal``'s threshold for ``scene`` (``AssistanceSignal.fits_on_episodes``) to the level at
    which it would have asked on the most doubtful of ``policy``'s own successful autonomous episodes of
    ``tasks`` (``episodes`` per task, seeds ``seed ..``), when that is above the threshold calibrated on
    the demonstrations; returns the evidence.

    Why: a fine-tuned version is calibrated on the demonstrations as its parent was, but served on its
    own episodes, and asked where an operator was not needed (docs/benchmarks/nights.md): a lift version
    fine-tuned on grasps of other objects is less sure of the cube's grasp than of the demonstrations'
    (``familiar``: lift-cube), and one that has learnt to grasp the hammer pauses above it before it does
    (``new``: the shifted tasks). The requests an operator is not needed for are those of the episodes
    the policy finishes alone: with the threshold at the highest level among N of them, a further such
    episode (exchangeable with them) asks with probability at most 1 / (N + 1), 4.8% for N = 20. The
    threshold is only ever raised; fewer than ``MIN_FIT_SUCCESSES`` successful episodes leave it as
    calibrated, as for a parent that fails on the new scenes."""
    from policy.evaluate import rollout_policy

    if not signal.fits_on_episodes:
        raise ValueError(f"signal {name!r} has no rule to fit on episodes")
    seeds = list(range(seed, seed + episodes))
    done = []
    for task in tasks:
        eps, _ = rollout_policy(policy, task, seeds, n_envs=min(4, episodes), progress=progress, signals={name: signal})
        signal.reset()
        done += [e for e in eps if e.success]
    evidence = {"tasks": list(tasks), "scene": scene, "episodes": episodes * len(tasks), "seed": seed}
    evidence["successes"] = len(done)
    if len(done) < MIN_FIT_SUCCESSES:
        return evidence | {"factor": None, "why": f"fewer than {MIN_FIT_SUCCESSES} successful episodes to fit on"}
    levels = [signal.episode_level(np.array([s[name] for s in e.signal_scores]), scene) for e in done]
    evidence |= {"levels": [round(v, 4) for v in levels], "asked": sum(v > signal.threshold for v in levels)}
    factor = max(1.0, max(levels) / signal.threshold)
    if factor > 1.0:
        signal.scale_threshold(scene, factor, evidence)
    return evidence | {"factor": factor}


@dataclass(frozen=True)
class TaskResult:
    task: str
    episodes: int
    successes: int
    seed: int

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes if self.episodes else 0.0

    def to_dict(self) -> dict:
        return {**asdict(self), "success_rate": self.success_rate}

    @classmethod
    def from_dict(cls, d: dict) -> TaskResult:
        return cls(str(d["task"]), int(d["episodes"]), int(d["successes"]), int(d["seed"]))

    @classmethod
    def from_episodes(cls, task: str, episodes: list, seed: int) -> TaskResult:
        """From the rolled-out episodes (anything with ``success``) of seeds ``seed ..``."""
        return cls(task, len(episodes), sum(bool(e.success) for e in episodes), seed)


def evaluate_episodes(
    policy: DiffusionPolicy, tasks: list[str], episodes: int, seed: int, progress: bool = True
) -> dict[str, list]:
    """Per task, the autonomous episodes (``PolicyEpisode``) on seeds ``seed .. seed + episodes - 1``,
    through the controller."""
    from policy.evaluate import rollout_policy

    seeds = list(range(seed, seed + episodes))
    return {t: rollout_policy(policy, t, seeds, n_envs=min(4, episodes), progress=progress)[0] for t in tasks}


def evaluate(
    policy: DiffusionPolicy, tasks: list[str], episodes: int, seed: int, progress: bool = True
) -> dict[str, TaskResult]:
    """Autonomous success per task on seeds ``seed .. seed + episodes - 1``, through the controller."""
    runs = evaluate_episodes(policy, tasks, episodes, seed, progress)
    return {t: TaskResult.from_episodes(t, eps, seed) for t, eps in runs.items()}


@dataclass(frozen=True)
class GateDecision:
    """promote: whether the candidate passed; reason: one line; evidence: the numbers it compared."""

    promote: bool
    reason: str
    evidence: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def gate(
    parent: dict[str, TaskResult],
    child: dict[str, TaskResult],
    train_task: str,
    target_tasks: list[str],
    tolerance: float,
    min_gain: float = 0.0,
) -> GateDecision:
    """Promote only if the child is not worse on ``train_task`` than the parent by more than
    ``tolerance`` and its mean success over ``target_tasks`` is higher than the parent's by more than
    ``min_gain``. Both must have been evaluated on the same tasks, episodes and seeds."""
    for task in {train_task, *target_tasks}:
        if task not in parent or task not in child:
            raise ValueError(f"task {task!r} was not evaluated for both versions")
        p, c = parent[task], child[task]
        if (p.episodes, p.seed) != (c.episodes, c.seed):
            raise ValueError(f"{task}: the versions were evaluated on different episodes ({p} vs {c})")
    base, new = parent[train_task].success_rate, child[train_task].success_rate
    target_base = float(np.mean([parent[t].success_rate for t in target_tasks]))
    target_new = float(np.mean([child[t].success_rate for t in target_tasks]))
    evidence = {
        "train_task": train_task,
        "target_tasks": list(target_tasks),
        "train_success": {"parent": base, "candidate": new},
        "target_success": {"parent": target_base, "candidate": target_new},
        "per_task": {t: {"parent": parent[t].to_dict(), "candidate": child[t].to_dict()} for t in parent},
        "tolerance": tolerance,
        "min_gain": min_gain,
    }
    if new < base - tolerance - 1e-12:
        why = f"worse on {train_task}: {new:.2f} against {base:.2f} (tolerance {tolerance:.2f})"
        return GateDecision(False, why, evidence)
    if not target_new > target_base + min_gain:
        why = f"not better on {', '.join(target_tasks)}: {target_new:.2f} against {target_base:.2f}" + (
            f" (needs more than +{min_gain:.2f})" if min_gain else ""
        )
        return GateDecision(False, why, evidence)
    why = (
        f"{', '.join(target_tasks)} {target_base:.2f} -> {target_new:.2f}; "
        f"{train_task} {base:.2f} -> {new:.2f} (tolerance {tolerance:.2f})"
    )
    return GateDecision(True, why, evidence)

"""Signals computed from the diffusion policy alone: ``denoising`` (the paper's metric),
``output-variance``, ``diff-dagger`` and ``stac``.

Each scores the whole batch of robots in as few network calls as its method allows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, fields, replace

import numpy as np
import torch
from tqdm import tqdm

from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    Patience,
    PerRobot,
    Scores,
    SignalConfig,
    SignalError,
    SignalInput,
    StepSet,
    TriggerState,
    check_positive_int,
    check_quantile,
    quantile_record,
)
from policy.uncertainty import UncertaintyConfig, UncertaintyEstimator
from sim.spaces import POS

NO_GRIPPER = slice(0, 9)  # every action dimension but the gripper
# the probe's centre: the "current" pose (the paper), the policy's next "action", or its "chunk" moved by
# the probe and read at its last executed step, the pose it will reach (the paper's metric on a chunked
# policy; on a chunk of one, the next action)
CENTERS = ("current", "action", "chunk")


def batched_scores(
    signal: AssistanceSignal, steps: StepSet, batch: int, progress: bool, desc: str, ids_offset: int = 0
) -> np.ndarray:
    """Scores independent recorded steps in batches (each step is its own robot, fresh state)."""
    out = []
    bar = tqdm(total=len(steps), desc=desc, disable=not progress, unit="step")
    try:
        for i in range(0, len(steps), batch):
            rows = np.arange(i, min(i + batch, len(steps)))
            ids = rows + ids_offset
            signal.reset(ids)
            out.append(signal.score(_input(steps, rows, ids)).value)
            signal.reset(ids)
            bar.update(len(rows))
    finally:
        bar.close()
    return np.concatenate(out) if out else np.zeros(0)


def _input(steps: StepSet, rows: np.ndarray, ids: np.ndarray) -> SignalInput:
    return SignalInput(torch.as_tensor(steps.obs[rows]), torch.as_tensor(steps.current[rows]), ids)


def subsample(steps: StepSet, limit: int, seed: int) -> StepSet:
    if len(steps) <= limit:
        return steps
    rows = np.sort(np.random.default_rng(seed).choice(len(steps), limit, replace=False))
    return steps.take(rows)


# -- denoising ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DenoisingConfig(UncertaintyConfig, SignalConfig):
    """The paper's metric: its settings are ``UncertaintyConfig``'s (one definition); threshold =
    ``quantile`` of U on held-out demos."""

    quantile: float = 0.95
    calibration_batch: int = 64
    center: str = "current"  # probe centre: "current" pose (the paper) or the policy's next "action"

    def __post_init__(self) -> None:
        super().__post_init__()  # validates the metric's settings
        check_quantile("quantile", self.quantile)
        check_positive_int("calibration_batch", self.calibration_batch)
        if self.center not in CENTERS:
            raise ValueError(f"center must be one of {CENTERS}, got {self.center!r}")

    def uncertainty(self) -> UncertaintyConfig:
        return UncertaintyConfig(**{f.name: getattr(self, f.name) for f in fields(UncertaintyConfig)})

    @classmethod
    def from_uncertainty(cls, config: UncertaintyConfig, **signal_settings) -> DenoisingConfig:
        return cls(**asdict(config), **signal_settings)


class DenoisingSignal(AssistanceSignal):
    name = "denoising"
    Config = DenoisingConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        metric = self.config.uncertainty()
        if self.config.center == "chunk":  # read where the chunk will be when the next one is sampled
            last = min(int(policy.config.n_action_steps), int(policy.config.action_horizon)) - 1
            metric = replace(metric, chunk_step=last)
        self.estimator = UncertaintyEstimator(metric)

    def score(self, batch: SignalInput) -> Scores:
        plan = None
        if self.config.center in ("action", "chunk"):  # the robot's chunk (sampled when not given)
            action = batch.action if batch.action is not None else self.sample_chunks(batch.obs, 1)[:, 0]
            center = self.policy.normalize_action(action[:, 0])
            if self.config.center == "chunk":  # the chunk moved by the probe, read where it will reach
                plan = self.policy.normalize_action(action).to(self.policy.device)
        else:
            center = self.policy.normalize_action(batch.current)
        result = self.estimator(  # the probe and the fits run where the policy's weights are
            self.policy.noise_prediction,
            batch.obs,
            center.to(self.policy.device),
            chunk=self.policy.config.action_horizon,
            alphas_cumprod=self.policy.schedule.alphas_cumprod,
            plan=plan,
        )
        return Scores(
            result.U.numpy(),
            {"D": result.D.numpy(), "var_g": result.var_g.numpy(), "modes": result.fit.n.numpy()},
            detail=result,
        )

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        values = batched_scores(self, data.val, self.config.calibration_batch, progress, "calibrate denoising")
        return quantile_record(values, self.config.quantile, "validation demonstrations")


# -- output variance ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class OutputVarianceConfig(SignalConfig):
    """Variance across ``num_samples`` sampled chunks, averaged over position dims and chunk steps
    (normalized action space)."""

    num_samples: int = 64
    quantile: float = 0.95
    max_calibration_steps: int = 2000

    def __post_init__(self) -> None:
        if not (isinstance(self.num_samples, int) and self.num_samples >= 2):
            raise ValueError(f"num_samples must be an integer >= 2, got {self.num_samples!r}")
        check_quantile("quantile", self.quantile)
        check_positive_int("max_calibration_steps", self.max_calibration_steps)


class OutputVarianceSignal(AssistanceSignal):
    name = "output-variance"
    Config = OutputVarianceConfig

    def score(self, batch: SignalInput) -> Scores:
        chunks = self.policy.normalize_action(self.sample_chunks(batch.obs, self.config.num_samples))
        var = chunks[..., POS].var(dim=1, unbiased=False)  # (B, C, 3)
        return Scores(var.mean(dim=(1, 2)).numpy().astype(np.float64))

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        val = subsample(data.val, self.config.max_calibration_steps, self.config.seed)
        values = batched_scores(self, val, 32, progress, "calibrate output-variance")
        return quantile_record(values, self.config.quantile, "validation demonstrations")


# -- Diff-DAgger ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DiffDaggerConfig(SignalConfig):
    """Diffusion loss of the policy's own action over all training steps k, ``noise_draws`` each.

    Threshold: the ``quantile`` of the same loss of demonstrated actions over (at most
    ``max_calibration_steps`` steps of) the training split; asks after ``patience`` consecutive
    steps over it.
    """

    noise_draws: int = 16
    quantile: float = 0.99
    patience: int = 2
    max_rows: int = 16384  # network rows per call
    max_calibration_steps: int = 1000

    def __post_init__(self) -> None:
        for name in ("noise_draws", "patience", "max_rows", "max_calibration_steps"):
            check_positive_int(name, getattr(self, name))
        check_quantile("quantile", self.quantile)


class DiffDaggerSignal(AssistanceSignal):
    name = "diff-dagger"
    Config = DiffDaggerConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self._over = Patience(self.config.patience)

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        self._over.reset(self._ids_for(robot_ids))

    @torch.no_grad()
    def diffusion_loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """obs (B, H, D) raw, action (B, C, 10) raw -> (B,) mean over k = 0..K-1 and the noise draws of
        ||ε_θ(o, √ᾱ_k a + √(1-ᾱ_k) ε, k) - ε||² / (C·10)."""
        policy = self.policy
        n_k, m = policy.config.num_train_steps, self.config.noise_draws
        x0 = policy.normalize_action(action)  # (B, C, D)
        b = x0.shape[0]
        ks = torch.arange(n_k)
        per_robot_rows = n_k * m
        robots_per_call = max(1, self.config.max_rows // per_robot_rows)
        out = []
        for i in range(0, b, robots_per_call):
            xb, ob = x0[i : i + robots_per_call], obs[i : i + robots_per_call]
            nb = xb.shape[0]
            # one "robot row" per (robot, k): obs repeated over k, the noise draws are the samples
            k = ks.repeat(nb)  # (nb*K,)
            x = xb.repeat_interleave(n_k, dim=0)[:, None].expand(-1, m, -1, -1)  # (nb*K, M, C, D)
            noise = torch.randn(x.shape, generator=self._generator)
            ab = policy.schedule.alphas_cumprod[k].view(-1, 1, 1, 1)
            xk = ab.sqrt() * x + (1 - ab).sqrt() * noise
            eps = policy.noise_prediction(ob.repeat_interleave(n_k, dim=0), xk, k)
            err = ((eps - noise) ** 2).mean(dim=(1, 2, 3)).view(nb, n_k)
            out.append(err.mean(dim=1))
        return torch.cat(out).double()

    def score(self, batch: SignalInput) -> Scores:
        action = batch.action if batch.action is not None else self.sample_chunks(batch.obs, 1)[:, 0]
        return Scores(self.diffusion_loss(batch.obs, action).numpy())

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return self._over.update(np.asarray(scores.value) > self.threshold, state.robot_ids)

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        train = subsample(data.train, self.config.max_calibration_steps, self.config.seed)
        values, bar = [], tqdm(total=len(train), desc="calibrate diff-dagger", disable=not progress, unit="step")
        try:
            for i in range(0, len(train), 16):
                rows = np.arange(i, min(i + 16, len(train)))
                values.append(
                    self.diffusion_loss(torch.as_tensor(train.obs[rows]), torch.as_tensor(train.action[rows])).numpy()
                )
                bar.update(len(rows))
        finally:
            bar.close()
        return quantile_record(np.concatenate(values), self.config.quantile, "training demonstrations")


# -- STAC (Sentinel) -----------------------------------------------------------------------------------------
def rbf_mmd2(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Biased MMD² between sample sets x (B, n, d) and y (B, m, d) with an RBF kernel whose bandwidth
    is the median pairwise distance of the pooled samples (per robot) -> (B,)."""
    z = torch.cat([x, y], dim=1)
    d2 = torch.cdist(z, z).pow(2)  # (B, n+m, n+m)
    n = z.shape[1]
    off = ~torch.eye(n, dtype=torch.bool)
    med = d2[:, off].median(dim=1).values.clamp_min(1e-12)  # squared median distance
    k = torch.exp(-d2 / med[:, None, None])
    nx = x.shape[1]
    kxx, kyy, kxy = k[:, :nx, :nx], k[:, nx:, nx:], k[:, :nx, nx:]
    return kxx.mean((1, 2)) + kyy.mean((1, 2)) - 2 * kxy.mean((1, 2))


@dataclass(frozen=True)
class StacConfig(SignalConfig):
    """Temporal consistency of sampled chunks; needs a policy with action_horizon > ``shift``.

    ``shift``: control steps between consecutive scores (1: scored every step). Threshold: the
    ``quantile`` of the per-episode maximum cumulative score over successful calibration rollouts.
    """

    num_samples: int = 64
    shift: int = 1
    quantile: float = 0.95

    def __post_init__(self) -> None:
        if not (isinstance(self.num_samples, int) and self.num_samples >= 2):
            raise ValueError(f"num_samples must be an integer >= 2, got {self.num_samples!r}")
        check_positive_int("shift", self.shift)
        check_quantile("quantile", self.quantile)


class StacSignal(AssistanceSignal):
    name = "stac"
    Config = StacConfig
    needs_rollouts = True

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        horizon = policy.config.action_horizon
        if horizon <= self.config.shift:
            raise SignalError(
                f"stac compares consecutive action chunks on their overlap: it needs a policy with "
                f"action_horizon > {self.config.shift}, this one predicts {horizon} step(s)"
            )
        self._previous: dict[int, torch.Tensor] = {}
        self._total = PerRobot(float)

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        ids = self._ids_for(robot_ids)
        self._total.reset(ids)
        if ids is None:
            self._previous.clear()
        else:
            for i in ids:
                self._previous.pop(i, None)

    def score(self, batch: SignalInput) -> Scores:
        s = self.config.shift
        chunks = self.policy.normalize_action(self.sample_chunks(batch.obs, self.config.num_samples))
        chunks = chunks[..., NO_GRIPPER]  # (B, n, C, 9)
        ids = [int(i) for i in batch.robot_ids]
        step = np.zeros(len(ids))
        have = [j for j, rid in enumerate(ids) if rid in self._previous]
        if have:
            prev = torch.stack([self._previous[ids[j]] for j in have])[:, :, s:].flatten(2)
            cur = chunks[have][:, :, :-s].flatten(2)
            step[have] = rbf_mmd2(prev.double(), cur.double()).clamp_min(0).numpy()
        total = np.zeros(len(ids))
        for j, rid in enumerate(ids):
            self._previous[rid] = chunks[j]
            self._total.set(rid, self._total.get(rid) + step[j])
            total[j] = self._total.get(rid)
        return Scores(total, {"step": step})

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        rollouts = data.rollouts
        assert rollouts is not None
        episodes = [rows for rows in rollouts.episodes() if rollouts.success[rows[0]]]
        if not episodes:
            raise SignalError("stac calibrates on successful rollouts; none of the given rollouts succeeded")
        peaks = replay_episodes(self, rollouts, episodes, progress, "calibrate stac", reduce=np.max)
        return quantile_record(peaks, self.config.quantile, f"{len(episodes)} successful policy rollouts")


def replay_series(
    signal: AssistanceSignal,
    steps: StepSet,
    episodes: list[np.ndarray],
    progress: bool,
    desc: str,
    batch: int = 16,
) -> list[np.ndarray]:
    """Feeds recorded episodes through a stateful signal in lockstep (one robot per episode, steps in
    order, fresh state per episode); returns each episode's score at every step."""
    out: list[np.ndarray] = []
    bar = tqdm(total=len(episodes), desc=desc, disable=not progress, unit="ep")
    try:
        for g in range(0, len(episodes), batch):
            group = episodes[g : g + batch]
            ids = np.arange(g, g + len(group)) + 1_000_000
            signal.reset(ids)
            series: list[list[float]] = [[] for _ in group]
            for t in range(max(len(r) for r in group)):
                live = [j for j, r in enumerate(group) if t < len(r)]
                rows = np.array([group[j][t] for j in live])
                scores = signal.score(_input(steps, rows, ids[live]))
                for j, v in zip(live, scores.value, strict=True):
                    series[j].append(float(v))
            signal.reset(ids)
            out += [np.asarray(s) for s in series]
            bar.update(len(group))
    finally:
        bar.close()
    return out


def replay_episodes(
    signal: AssistanceSignal,
    steps: StepSet,
    episodes: list[np.ndarray],
    progress: bool,
    desc: str,
    reduce: Callable[[np.ndarray], float],
    batch: int = 16,
) -> np.ndarray:
    """``replay_series`` with each episode's score sequence reduced to one number."""
    return np.array([reduce(s) for s in replay_series(signal, steps, episodes, progress, desc, batch)])

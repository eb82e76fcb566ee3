"""``choice``: ask where the policy has a choice of which way to go: its own samples of the place its
next executed action reaches lie on both sides of the gripper.

S samples of the policy's chunk are drawn by its own sampler (DDIM from S noise draws, each robot's
draws its own), and each sample's position at the chunk's last executed step (``n_action_steps``) is
taken: the place the chunk will reach. Per axis, the targets' spread is their interquartile range over
1.349 (a standard deviation for a Gaussian, robust to one stray sample), counted only where the
quartiles lie on both sides of the current position: some samples go one way, some the other. The
score is the largest axis's, in metres.

Why (docs/signals.md, "choice-stall"):

- The gripper is left out. Averaged over all ten action dimensions, as ``spread`` does, a choice of
  where to go barely moves the score, while opening or closing the gripper dominates it: ``spread``
  peaks at the cup grasp and at the drawer handle, where a few operator steps change nothing.
- The probe is the policy's own samples, not a ball around the current pose. The paper's metric
  probes a ball whose radius contains the next target, so its mixtures find one mode on nearly
  every state and the score follows the variance term.
- Both sides: targets that all go the same way and differ only in how far (a lift's height, a carry's
  pace) are not a choice that a few operator steps make.
- Measured on the development seeds (docs/signals.md, "choice-stall"): the score peaks at the drawer's
  first step, where the choice of drawer is made (docs/benchmarks/hitl.md, "The floor"), and crosses
  the threshold in none of the lift-cube episodes the policy finishes alone.

Threshold: ``stride_ratio`` times the policy's stride, the median distance its chunk moves the end
effector per step at the open-gripper steps of the validation demonstrations (as ``stall`` measures
it): the targets disagree by that share of a step. No failure data and no operator labels. A
quantile of the score over the same demonstrations would not do: the drawer's first steps are in
every demonstration, so a threshold that covers most of the demonstrations' states covers them too
(docs/signals.md).

Trigger: the robot wants help after ``patience`` consecutive steps over the threshold. **Hand-back**
(LazyDAgger's two thresholds): once it wanted help, it keeps wanting it while the score stays over
``return_ratio`` times the threshold, on the operator's steps and the steps after a hand-back alike.
On the paper's protocol (requests of ``budget`` operator steps) the robot so asks again after a
request when the choice is still open, and hands back for good once the operator's steps settled it.

Cost: S rows per robot through each of the sampler's steps (with S = 16 and 10 DDIM steps: 160 rows
per robot-step in 10 calls); ``hitl bench signals`` measures it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    Patience,
    PerRobot,
    RobotNoise,
    Scores,
    SignalConfig,
    SignalError,
    SignalInput,
    TriggerState,
    check_positive_int,
)
from policy.signals.sampling import subsample
from sim.spaces import GRIPPER, POS

IQR_TO_STD = 1.349  # the interquartile range of a unit Gaussian


def _check_ratio(name: str, r: object, most: float) -> None:
    if not (isinstance(r, int | float) and not isinstance(r, bool) and math.isfinite(r) and 0 < r <= most):
        raise SignalError(f"{name} must be in (0, {most:g}], got {r!r}")


@dataclass(frozen=True)
class ChoiceConfig(SignalConfig):
    """num_samples: S samples of the chunk per robot-step; stride_ratio: the threshold, as a share of
    the policy's stride; patience: consecutive steps over it before the robot asks; return_ratio: once
    it asked, it keeps wanting help while the score is over this share of the threshold (1: the same
    threshold both ways); max_calibration_steps, calibration_batch: validation steps scored, and per
    call."""

    num_samples: int = 16
    stride_ratio: float = 0.25
    patience: int = 1
    return_ratio: float = 0.5
    max_calibration_steps: int = 3000
    calibration_batch: int = 64

    def __post_init__(self) -> None:
        check_positive_int("num_samples", self.num_samples)
        if self.num_samples < 4:
            raise SignalError(f"num_samples must be >= 4 (an interquartile range), got {self.num_samples}")
        _check_ratio("stride_ratio", self.stride_ratio, 10.0)
        check_positive_int("patience", self.patience)
        _check_ratio("return_ratio", self.return_ratio, 1.0)
        check_positive_int("max_calibration_steps", self.max_calibration_steps)
        check_positive_int("calibration_batch", self.calibration_batch)


def reach(samples: torch.Tensor, n_action_steps: int) -> torch.Tensor:
    """(B, S, C, 10) raw sampled chunks -> (B, S, 3): each sample's position at its last executed step."""
    n = min(int(n_action_steps), samples.shape[2])
    return samples[:, :, n - 1, POS].double()


def where_to_go(targets: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """(B, S, 3) target positions, (B, 3) current positions -> (B,) metres: per axis the targets' robust
    spread (interquartile range / 1.349), where their quartiles lie on both sides of the current
    position (else 0); the largest axis's."""
    d = targets - current.double()[:, None, :]
    q = torch.quantile(d, torch.tensor([0.25, 0.75], dtype=torch.float64), dim=1)  # (2, B, 3)
    both_sides = (q[0] < 0) & (q[1] > 0)
    return torch.where(both_sides, (q[1] - q[0]) / IQR_TO_STD, torch.zeros_like(q[0])).amax(dim=-1)


class Hysteresis:
    """Per-robot two-threshold trigger: a robot wants help after ``patience`` steps over the ask level,
    then keeps wanting it while its score stays over the return level (LazyDAgger)."""

    def __init__(self, patience: int) -> None:
        self._run = Patience(patience)
        self._engaged = PerRobot(bool)

    def update(self, over: np.ndarray, still_over: np.ndarray, robot_ids: Iterable[int]) -> np.ndarray:
        """over / still_over: (B,) bool, over the ask level / over the return level -> (B,) wants help."""
        ids = [int(r) for r in robot_ids]
        asks = self._run.update(np.asarray(over, dtype=bool), ids)
        out = np.zeros(len(ids), dtype=bool)
        for j, rid in enumerate(ids):
            engaged = bool(asks[j]) or (self._engaged.get(rid) and bool(still_over[j]))
            self._engaged.set(rid, engaged)
            out[j] = engaged
        return out

    def release(self, robot_ids: Iterable[int]) -> None:
        """These robots' requests are settled: they want help again only over the ask level."""
        self._engaged.reset([int(r) for r in robot_ids])

    def reset(self, robot_ids: list[int] | None) -> None:
        self._run.reset(robot_ids)
        self._engaged.reset(robot_ids)


class ChoiceSignal(AssistanceSignal):
    name = "choice"
    Config = ChoiceConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self._noise = RobotNoise(self.config.seed)  # each robot's draws, whatever its batch
        self._trigger = Hysteresis(self.config.patience)

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        ids = self._ids_for(robot_ids)
        self._noise.reset(ids)
        self._trigger.reset(ids)

    @torch.no_grad()
    def targets(self, obs: torch.Tensor, robot_ids: np.ndarray) -> torch.Tensor:
        """(B, S, 3) where S samples of each robot's chunk reach (``reach``), from its own noise."""
        cfg, pc = self.config, self.policy.config
        s = cfg.num_samples
        noise = self._noise.randn(robot_ids, (s, pc.action_horizon, pc.action_dim))  # (B, S, C, D)
        rep = torch.as_tensor(obs, dtype=torch.float32).repeat_interleave(s, dim=0)
        chunks = self.policy.predict_action_chunk(rep, noise=noise.reshape(-1, pc.action_horizon, pc.action_dim))
        return reach(chunks.reshape(len(robot_ids), s, *chunks.shape[1:]).cpu(), pc.n_action_steps)

    def spread(self, obs: torch.Tensor, current: torch.Tensor, robot_ids: np.ndarray) -> np.ndarray:
        """(B,) metres: ``where_to_go`` of each robot's sampled targets around its current position."""
        return where_to_go(self.targets(obs, robot_ids), torch.as_tensor(current)[:, POS]).numpy()

    def score(self, batch: SignalInput) -> Scores:
        value = self.spread(batch.obs, batch.current, batch.robot_ids)
        return Scores(value, {"choice": value})

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return self.trigger(np.asarray(scores.value, dtype=np.float64), self.threshold, state.robot_ids)

    def trigger(self, value: np.ndarray, threshold: float, robot_ids: np.ndarray) -> np.ndarray:
        """The rule behind ``wants_help`` at ``threshold`` (a signal that holds a ``choice`` applies its
        own): ``patience`` steps over it, then while over ``return_ratio`` of it."""
        return self._trigger.update(value > threshold, value > self.config.return_ratio * threshold, robot_ids)

    def release(self, robot_ids: Iterable[int]) -> None:
        """The robots' requests are settled (an operator's step did it): from now on they want help only
        over the threshold again."""
        self._trigger.release(robot_ids)

    def explain(self, scores: Scores, j: int) -> str | None:
        cm = 100 * float(scores.parts["choice"][j])
        return f"the policy has a choice of which way to go: its targets spread {cm:.2g} cm to either side"

    def episode_level(self, scores: np.ndarray, scene: str) -> float:
        """The level it would have asked at: the largest value that ``patience`` consecutive steps all
        reached (0 for a shorter episode)."""
        return window_level(scores, self.config.patience)

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        val = subsample(data.val, self.config.max_calibration_steps, self.config.seed)
        size, values, motion, opened = self.config.calibration_batch, [], [], []
        n = min(int(self.policy.config.n_action_steps), self.policy.config.action_horizon)
        for i in tqdm(range(0, len(val), size), desc="calibrate choice", disable=not progress, unit="batch"):
            rows = np.arange(i, min(i + size, len(val)))
            self._noise.reset(list(rows))
            current = torch.as_tensor(val.current[rows])
            targets = self.targets(torch.as_tensor(val.obs[rows]), rows)
            values.append(where_to_go(targets, current[:, POS]).numpy())
            # the stride: how far the policy's median sample moves the end effector per step
            motion.append((targets.median(dim=1).values - current[:, POS].double()).norm(dim=-1).numpy() / n)
            opened.append((current[:, GRIPPER] <= 0).numpy())
        if not values:
            raise SignalError("choice: no validation demonstrations to calibrate on")
        values, motion, opened = np.concatenate(values), np.concatenate(motion), np.concatenate(opened)
        if not opened.any():
            raise SignalError("choice: the validation demonstrations have no open-gripper steps")
        stride = float(np.median(motion[opened]))
        if not stride > 0:
            raise SignalError("choice: the policy does not move at the validation demonstrations' open-gripper steps")
        threshold = self.config.stride_ratio * stride
        return {
            "threshold": threshold,
            "quantile": None,
            "samples": int(len(values)),
            "source": f"validation demonstrations: {self.config.stride_ratio:g} of the policy's stride",
            "stride": stride,
            "over_share": float(np.mean(values > threshold)),  # of the validation steps
            "stats": {"mean": float(values.mean()), "median": float(np.median(values)), "max": float(values.max())},
        }


def window_level(scores: np.ndarray, patience: int) -> float:
    """The largest value that ``patience`` consecutive entries of ``scores`` all reach (0 when shorter)."""
    v = np.asarray(scores, dtype=np.float64)
    if len(v) < patience:
        return 0.0
    return float(np.lib.stride_tricks.sliding_window_view(v, patience).min(axis=1).max())

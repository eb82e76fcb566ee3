"""``spread``: the denoising field read at a noise level k > 0, around the policy's own next action,
as a posterior spread; plus an observation-novelty term.

Derivation (docs/spread.md). For a diffusion model trained with ε-prediction, Tweedie's formula
turns the noise prediction at level k into the posterior mean of the clean action:

    x̂_0(x_k) = (x_k - sqrt(1 - ᾱ_k) ε_θ(o, x_k, k)) / sqrt(ᾱ_k) ≈ E[a | x_k, o],

and its Jacobian is the posterior covariance: ∂x̂_0/∂x_k = sqrt(ᾱ_k) Cov[a | x_k, o] / (1 - ᾱ_k).
Noising the policy's own next action a* to level k (x_k = sqrt(ᾱ_k) a* + sqrt(1 - ᾱ_k) ξ) and
denoising it back in one call therefore spreads the S estimates x̂_0 by how much the policy's action
distribution allows: for a Gaussian policy N(μ, s² I) the spread is

    Var_ξ[x̂_0] = (1 - ᾱ_k) / ᾱ_k · (ᾱ_k s² / (ᾱ_k s² + 1 - ᾱ_k))²,

increasing in s (the paper's Var_g at k = 0 grows as s *shrinks*), and a multimodal policy sends
the estimates to different modes, which adds the squared distance between modes. Unlike the k = 0
field it does not depend on where the probe sits relative to the target: the probe is always
centred on the action the robot is about to take.

The observation term is how far the observation lies outside the range of the demonstrations the
signal was calibrated on (the policy's training demonstrations), in units of that range, averaged
over dimensions: 0 inside their box. It is what tells a state the policy never saw demonstrated from
one it saw and is merely unsure about. The box is recorded with the calibration
(``novelty_range``), not read from the policy's observation normalizer: fine-tuning widens the
normalizer to cover the takeovers (``policy.finetune``), so that a lift policy fine-tuned on a few
grasps of a hammer would otherwise find every hammer scene familiar, approach included, which it
never saw done (docs/benchmarks/nights.md). A calibration recorded before the box was (the bundled
policies' until they are recalibrated) measures against the normalizer, which is the same box for a
policy fitted on those demonstrations.

    score = spread / spread_scale + novelty_weight · novelty  (+ hover_weight · hover / hover_scale)

``spread_scale`` is the median spread on held-out demonstrations (set by ``calibrate``, so the
two terms are in comparable units); the threshold is the ``quantile`` of the score there.
Cost: one noise-network call on S = 32 rows per robot (the paper's metric: 128 rows, then mixture
fits), and no extra sampling when the controller passes the robot's chunk.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from policy.normalizer import MinMaxNormalizer
from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    RobotNoise,
    Scores,
    SignalConfig,
    SignalError,
    SignalInput,
    check_positive_int,
    check_quantile,
    quantile_record,
)
from policy.uncertainty import sample_ball
from sim.spaces import POS

DIMS = {"pos": POS, "all": slice(None)}


@dataclass(frozen=True)
class SpreadConfig(SignalConfig):
    """num_samples: S re-noisings of the next action; noise_step: k of the schedule's
    ``num_train_steps``; dims: action dimensions whose spread counts ("pos" or "all");
    novelty_weight: weight of the observation-novelty term (0: the field alone); hover_weight: weight
    of the optional unit-direction term of the k = 0 field over a ball of ``radius`` around the current
    pose (0, off: tried and set aside on development seeds, docs/spread.md). Defaults as chosen there."""

    num_samples: int = 32
    noise_step: int = 60
    dims: str = "all"
    novelty_weight: float = 1.0
    hover_weight: float = 0.0
    radius: float = 0.05  # the hover term's probe ball (normalized action space)
    quantile: float = 0.95
    calibration_batch: int = 64

    def __post_init__(self) -> None:
        check_positive_int("num_samples", self.num_samples)
        if self.num_samples < 2:
            raise ValueError(f"num_samples must be >= 2, got {self.num_samples}")
        if not (isinstance(self.noise_step, int) and not isinstance(self.noise_step, bool) and self.noise_step >= 1):
            raise ValueError(f"noise_step must be an integer >= 1, got {self.noise_step!r}")
        if self.dims not in DIMS:
            raise ValueError(f"dims must be one of {tuple(DIMS)}, got {self.dims!r}")
        for name in ("novelty_weight", "hover_weight"):
            w = getattr(self, name)
            if not (isinstance(w, int | float) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {w!r}")
        if not (isinstance(self.radius, int | float) and 0 < self.radius <= 1):
            raise ValueError(f"radius must be in (0, 1], got {self.radius!r}")
        check_quantile("quantile", self.quantile)
        check_positive_int("calibration_batch", self.calibration_batch)


def renoised_estimates(
    eps_fn: Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor],
    obs: torch.Tensor,
    center: torch.Tensor,
    alpha_bar: float,
    k: int,
    xi: torch.Tensor,
) -> torch.Tensor:
    """Noises ``center`` to level k with each of the S draws in ``xi`` and denoises all in one call
    (Tweedie).

    eps_fn(obs, actions (B, S, C, D), k) -> noise of the same shape; center: (B, C, D) normalized
    action chunks; alpha_bar: ᾱ_k; xi: (B, S, C, D) standard normal. Returns x̂_0: (B, S, C, D).
    """
    x_k = math.sqrt(alpha_bar) * center[:, None] + math.sqrt(1 - alpha_bar) * xi
    eps = eps_fn(obs, x_k, k)
    return (x_k - math.sqrt(1 - alpha_bar) * eps) / math.sqrt(alpha_bar)


def observation_novelty(normalized: torch.Tensor) -> torch.Tensor:
    """(B, H, obs_dim) observations normalized to the training range [0, 1] -> (B,) mean distance
    outside [0, 1] over dimensions (of the newest frame); 0 for an observation inside the range."""
    last = normalized[:, -1]
    return (torch.relu(last - 1) + torch.relu(-last)).mean(dim=-1)


def demonstrations_range(policy, obs: np.ndarray | torch.Tensor) -> dict[str, list[float]]:
    """The box of ``obs`` (M, H, obs_dim) raw demonstrations in the policy's network frame, as the
    policy's own normalizer fits its training data (``MinMaxNormalizer.fit``): {"low", "span"}. For a
    policy that sees, ``obs`` is seen (M, H, seen_dim): the box spans its cameras' features too."""
    obs_t = torch.as_tensor(np.asarray(obs), dtype=torch.float32)
    if len(obs_t) == 0:
        raise SignalError("spread: no demonstrations to take the observation range from")
    box = MinMaxNormalizer(obs_t.shape[-1]).fit(policy.frame_obs(obs_t))
    return {"low": box.low.tolist(), "span": box.span.tolist()}


def novelty_against(policy, obs: torch.Tensor, box: dict | None) -> torch.Tensor:
    """(B,) ``observation_novelty`` of ``obs`` (B, H, obs_dim) raw against ``box``
    (``demonstrations_range``), or against the policy's observation normalizer when None."""
    if box is None:  # the state's own range (a seeing policy's features have none in its normalizer)
        return observation_novelty(policy.normalize_obs(obs)[..., : policy.config.obs_dim])
    low = torch.as_tensor(box["low"], dtype=torch.float32)
    span = torch.as_tensor(box["span"], dtype=torch.float32)
    if low.shape != (policy.seen_dim,) or span.shape != low.shape or not bool((span > 0).all()):
        raise SignalError(f"spread: novelty_range needs {policy.seen_dim} lows and positive spans")
    framed = policy.frame_obs(torch.as_tensor(obs, dtype=torch.float32))
    return observation_novelty((framed - low.to(framed.device)) / span.to(framed.device))


class SpreadSignal(AssistanceSignal):
    name = "spread"
    Config = SpreadConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        k = self.config.noise_step
        if k >= policy.config.num_train_steps:
            raise SignalError(f"noise_step {k} is outside the policy's {policy.config.num_train_steps} diffusion steps")
        self._noise = RobotNoise(self.config.seed)  # each robot's draws, whatever its batch

    def reset(self, robot_ids=None) -> None:
        self._noise.reset(robot_ids)

    @torch.no_grad()
    def parts(self, batch: SignalInput, novelty_range: dict | None = None) -> dict[str, np.ndarray]:
        """(B,) spread and novelty (against ``novelty_range``, ``novelty_against``), before scaling."""
        policy, cfg = self.policy, self.config
        action = batch.action if batch.action is not None else self.sample_chunks(batch.obs, 1)[:, 0]
        center = policy.normalize_action(action)
        xi = self._noise.randn(batch.robot_ids, (cfg.num_samples, *center.shape[1:]))
        abar = float(policy.schedule.alphas_cumprod[cfg.noise_step])
        x0 = renoised_estimates(policy.noise_prediction, batch.obs, center, abar, cfg.noise_step, xi)
        spread = x0[..., DIMS[cfg.dims]].double().var(dim=1, unbiased=False).mean(dim=(1, 2))
        novelty = novelty_against(policy, batch.obs, novelty_range).double()
        out = {"spread": spread.numpy(), "novelty": novelty.numpy()}
        if cfg.hover_weight > 0:
            out["hover"] = self._hover(batch).numpy()
        return out

    def _hover(self, batch: SignalInput) -> torch.Tensor:
        """(B,) 1 - |mean unit denoising direction|² of the k = 0 field over a ball of ``radius`` around
        the current pose: 0 when every probe point is pulled the same way (the policy is going
        somewhere), near 1 when the pull is radial (its target is inside the ball: it stays put)."""
        policy, cfg = self.policy, self.config
        center = policy.normalize_action(batch.current)  # (B, D)
        offsets = torch.cat(
            [sample_ball(1, cfg.num_samples, cfg.radius, self._noise.generator(i)) for i in batch.robot_ids]
        )
        probe = center[:, None, :].repeat(1, cfg.num_samples, 1)
        probe[..., POS] += offsets
        chunk = policy.config.action_horizon
        eps = policy.noise_prediction(batch.obs, probe[:, :, None, :].expand(-1, -1, chunk, -1), 0)
        v = eps[:, :, 0, POS].double()
        unit = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return 1 - (unit.mean(dim=1) ** 2).sum(-1)

    def combine(self, parts: dict[str, np.ndarray], calibration: dict | None) -> np.ndarray:
        """Before calibration each term is taken in its own units (scales 1)."""
        cal, cfg = calibration or {}, self.config
        value = parts["spread"] / cal.get("spread_scale", 1.0) + cfg.novelty_weight * parts["novelty"]
        if cfg.hover_weight > 0:
            value = value + cfg.hover_weight * parts["hover"] / cal.get("hover_scale", 1.0)
        return value

    def score(self, batch: SignalInput) -> Scores:
        """Before calibration the spread is taken in the normalized action space's own units (scale 1)."""
        parts = self.parts(batch, (self.calibration or {}).get("novelty_range"))
        return Scores(self.combine(parts, self.calibration), parts)

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        val, size = data.val, self.config.calibration_batch
        box = demonstrations_range(self.policy, data.train.obs)
        chunks = []
        for i in tqdm(range(0, len(val), size), desc="calibrate spread", disable=not progress, unit="batch"):
            rows = np.arange(i, min(i + size, len(val)))
            chunks.append(self.parts(SignalInput(val.obs[rows], val.current[rows], rows), box))
        if not chunks:
            raise SignalError("spread: no validation demonstrations to calibrate on")
        parts = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
        scales = {"spread_scale": float(np.median(parts["spread"]))}
        if "hover" in parts:
            scales["hover_scale"] = float(np.median(parts["hover"]))
        for name, value in scales.items():
            if not value > 0:
                raise SignalError(f"spread: the validation demonstrations give a zero median for {name}")
        record = quantile_record(self.combine(parts, scales), self.config.quantile, "validation demonstrations")
        return {**record, **scales, "novelty_max": float(parts["novelty"].max()), "novelty_range": box}

"""The denoising-vector-field uncertainty metric (paper, "Denoising-based uncertainty metric").

For every robot b of a batch:

1. draw S end-effector positions uniformly in the ball of radius r around the
   current end-effector position, in the policy's normalized action space; the
   other action dimensions (orientation, gripper) hold the current values and,
   for action chunks, every step of the chunk holds the same sample;
2. evaluate the noise predictor at k = 0 on them and keep the position
   components of the predicted noise of chunk step ``chunk_step`` (default 0,
   the action executed next): the denoising vectors V (S, 3);
3. fit Gaussian mixtures with n = 1..N modes to V and keep the best by the
   configured criterion (``gmm`` module);
4. score ``U = D + alpha * Var_g`` with D the mean over ordered pairs of modes of
   1 - cosine similarity of the mode means (0 for one mode) and Var_g the
   weight-averaged total variance of the vectors assigned to each mode.

The estimator only needs a callable ``eps_fn(obs, actions, k) -> noise`` with
actions of shape (B, S, C, D), so it runs on analytic fields as well as on
``DiffusionPolicy.noise_prediction``. One call scores the whole fleet.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch

from policy.gmm import BACKENDS, CRITERIA, MixtureFit, astuple_fit, fit_mixtures, warm_up
from sim.spaces import POS

EpsFn = Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]
DIRECTIONS = ("raw", "unit")


@dataclass(frozen=True)
class UncertaintyConfig:
    num_samples: int = 128
    radius: float = 0.05  # normalized action space, as in the paper
    max_modes: int = 4
    criterion: str = "bic"
    alpha: float = 0.1
    backend: str = "auto"  # numba on CPU, torch on an accelerator (gmm.BACKENDS)
    chunk_step: int = 0
    reg_covar: float = 1e-6
    seed: int = 0
    # variants (the paper's metric is the default: raw vectors of the field at k = 0)
    directions: str = "raw"  # "unit": each vector scaled to length 1 before the fit
    noise_step: int = 0  # k at which the field is evaluated (the probe is then noised to level k)

    def __post_init__(self) -> None:
        if not (isinstance(self.num_samples, int) and self.num_samples >= 2):
            raise ValueError(f"num_samples must be an integer >= 2, got {self.num_samples!r}")
        if not (isinstance(self.radius, int | float) and 0 < self.radius <= 1):
            raise ValueError(f"radius must be in (0, 1] (normalized action space), got {self.radius!r}")
        if not (isinstance(self.max_modes, int) and 1 <= self.max_modes <= self.num_samples // 2):
            raise ValueError(f"max_modes must be an integer in [1, num_samples / 2], got {self.max_modes!r}")
        if self.criterion not in CRITERIA:
            raise ValueError(f"criterion must be one of {CRITERIA}, got {self.criterion!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if not (isinstance(self.alpha, int | float) and math.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError(f"alpha must be a finite number >= 0, got {self.alpha!r}")
        if not (isinstance(self.chunk_step, int) and self.chunk_step >= 0):
            raise ValueError(f"chunk_step must be an integer >= 0, got {self.chunk_step!r}")
        if not self.reg_covar > 0:
            raise ValueError(f"reg_covar must be > 0, got {self.reg_covar!r}")
        if self.directions not in DIRECTIONS:
            raise ValueError(f"directions must be one of {DIRECTIONS}, got {self.directions!r}")
        if not (isinstance(self.noise_step, int) and not isinstance(self.noise_step, bool) and self.noise_step >= 0):
            raise ValueError(f"noise_step must be an integer >= 0, got {self.noise_step!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class UncertaintyResult:
    """One robot's score and everything the console draws (normalized action space).

    samples, vectors: (S, 3); labels: (S,); means: (n, 3); weights: (n,).
    """

    samples: np.ndarray
    vectors: np.ndarray
    labels: np.ndarray
    means: np.ndarray
    weights: np.ndarray
    n: int
    D: float
    var_g: float
    U: float

    def to_world(self, normalizer) -> WorldField:
        """The probe samples in metres (world frame) and the denoising directions (-ε, rescaled per
        axis from the normalized action space by ``normalizer``, the policy's action normalizer) of the
        samples and of the mode means, for the console's and the segments' arrows."""
        low = normalizer.low[POS].numpy().astype(np.float64)
        span = normalizer.span[POS].numpy().astype(np.float64)
        return WorldField(self.samples * span + low, -self.vectors * span, self.labels, -self.means * span)


@dataclass(frozen=True)
class WorldField:
    """A denoising field in world units. samples: (S, 3) m; vectors: (S, 3) denoising directions in
    m per unit noise; labels: (S,) mode of each sample; means: (n, 3) the modes' mean denoising directions
    (world-scaled, like ``vectors``)."""

    samples: np.ndarray
    vectors: np.ndarray
    labels: np.ndarray
    means: np.ndarray

    def arrow_scale(self, longest: float = 0.02) -> float:
        """Metres per unit vector so that the longest arrow is ``longest`` metres (0 for a null field)."""
        top = float(np.linalg.norm(self.vectors, axis=1).max()) if len(self.vectors) else 0.0
        return longest / top if top > 0 else 0.0


@dataclass
class UncertaintyBatch:
    """Batched tensors: samples/vectors (B, S, 3), labels (B, S), means (B, N, 3), weights (B, N),
    n, D, var_g, U: (B,)."""

    samples: torch.Tensor
    vectors: torch.Tensor
    fit: MixtureFit
    D: torch.Tensor
    var_g: torch.Tensor
    U: torch.Tensor

    def __len__(self) -> int:
        return self.U.shape[0]

    def robot(self, i: int) -> UncertaintyResult:
        n = int(self.fit.n[i])
        return UncertaintyResult(
            samples=self.samples[i].numpy(),
            vectors=self.vectors[i].numpy(),
            labels=self.fit.labels[i].numpy(),
            means=self.fit.means[i, :n].numpy(),
            weights=self.fit.weights[i, :n].numpy(),
            n=n,
            D=float(self.D[i]),
            var_g=float(self.var_g[i]),
            U=float(self.U[i]),
        )


def sample_ball(b: int, s: int, radius: float, g: torch.Generator) -> torch.Tensor:
    """(b, s, 3) offsets uniform in the 3D ball of ``radius``."""
    direction = torch.randn((b, s, 3), generator=g)
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    r = radius * torch.rand((b, s, 1), generator=g) ** (1 / 3)
    return direction * r


def mode_divergence(means: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """D: means (B, N, d), n (B,) -> (B,) mean over ordered pairs i != j < n of 1 - cos(g_i, g_j)."""
    unit = means / means.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = unit @ unit.transpose(1, 2)  # (B, N, N)
    k = torch.arange(means.shape[1])
    valid = (k[None, :] < n[:, None]).to(means.dtype)
    pair = valid[:, :, None] * valid[:, None, :] * (1 - torch.eye(means.shape[1], dtype=means.dtype))
    pairs = (n * (n - 1)).to(means.dtype)
    return torch.where(pairs > 0, ((1 - cos) * pair).sum((1, 2)) / pairs.clamp_min(1), torch.zeros_like(pairs))


def mixture_variance(vectors: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Var_g: vectors (B, S, d), labels (B, S), weights (B, N) -> (B,) sum_i w_i * tr Cov(vectors in mode i)."""
    n_modes = weights.shape[1]
    onehot = torch.nn.functional.one_hot(labels, n_modes).to(vectors.dtype)  # (B, S, N)
    count = onehot.sum(1)  # (B, N)
    mean = torch.einsum("bsn,bsd->bnd", onehot, vectors) / count.clamp_min(1)[..., None]
    sq = torch.einsum("bsn,bsd->bn", onehot, vectors**2) / count.clamp_min(1)
    var = (sq - (mean**2).sum(-1)).clamp_min(0)
    return (weights * torch.where(count > 0, var, torch.zeros_like(var))).sum(1)


class UncertaintyEstimator:
    """Scores a batch of robots in one call; deterministic for a given ``config.seed`` and call order."""

    def __init__(self, config: UncertaintyConfig | None = None) -> None:
        self.config = config or UncertaintyConfig()
        self._generator = torch.Generator().manual_seed(self.config.seed)
        if self.config.backend in ("auto", "numba"):
            warm_up()  # compiled (or read from numba's cache) now, not in the first control tick

    def reset(self) -> None:
        self._generator.manual_seed(self.config.seed)

    def probe(
        self, center: torch.Tensor, chunk: int, plan: torch.Tensor | None = None, step: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """center: (B, D) normalized current action -> (positions (B, S, 3), actions (B, S, C, D)), on
        ``center``'s device (the offsets are drawn on the CPU generator: the same probe on every device).
        With ``plan`` (B, C, D), a normalized chunk: the probe is the chunk moved by each offset (every
        step by the same), and the positions are those of its step ``step``."""
        cfg = self.config
        b, d = center.shape
        offsets = sample_ball(b, cfg.num_samples, cfg.radius, self._generator).to(center.device)
        if plan is not None:
            actions = plan[:, None].repeat(1, cfg.num_samples, 1, 1)
            actions[..., POS] += offsets[:, :, None, :]
            return actions[:, :, step, POS], actions
        actions = center[:, None, :].repeat(1, cfg.num_samples, 1)
        actions[..., POS] += offsets
        return actions[..., POS], actions[:, :, None, :].expand(b, cfg.num_samples, chunk, d)

    @torch.no_grad()
    def __call__(
        self,
        eps_fn: EpsFn,
        obs: torch.Tensor,
        center: torch.Tensor,
        chunk: int = 1,
        alphas_cumprod: torch.Tensor | None = None,
        plan: torch.Tensor | None = None,
    ) -> UncertaintyBatch:
        """obs: whatever ``eps_fn`` takes, batched over B robots; center: (B, D) current end-effector
        action (pose + gripper) in the normalized action space; chunk: the predictor's chunk length;
        alphas_cumprod: (K,) the noise schedule's ᾱ, needed when ``noise_step`` > 0 (the probe is
        scaled by sqrt(ᾱ_k), as the forward process scales clean actions; the field is read there).

        The probe, the field and the mixture fits run on ``center``'s device (an accelerator's when the
        caller puts it there); the score is computed, and the batch returned, on the CPU.

        plan: (B, C, D) a normalized chunk to probe around instead (``probe``): the chunk is moved by
        each offset and the field is read at its step ``chunk_step``, the pose it will reach there."""
        cfg = self.config
        center = torch.as_tensor(center).float()
        if center.dim() != 2 or center.shape[1] < 3:
            raise ValueError(f"center must have shape (B, D >= 3), got {tuple(center.shape)}")
        if not torch.isfinite(center).all():
            raise ValueError("center has NaN or inf entries")
        if not cfg.chunk_step < chunk:
            raise ValueError(f"chunk_step {cfg.chunk_step} is outside the chunk of length {chunk}")
        if plan is not None and tuple(plan.shape) != (center.shape[0], chunk, center.shape[1]):
            raise ValueError(
                f"plan must have shape {(center.shape[0], chunk, center.shape[1])}, got {tuple(plan.shape)}"
            )
        samples, actions = self.probe(center, chunk, plan, cfg.chunk_step)
        if cfg.noise_step > 0:
            if alphas_cumprod is None or cfg.noise_step >= len(alphas_cumprod):
                raise ValueError(f"noise_step {cfg.noise_step} needs the schedule's alphas_cumprod covering it")
            actions = actions * float(alphas_cumprod[cfg.noise_step]) ** 0.5
        eps = eps_fn(obs, actions, cfg.noise_step)
        vectors = eps[:, :, cfg.chunk_step, POS].to(center.device, torch.float64)
        if cfg.directions == "unit":
            vectors = vectors / vectors.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        fit = fit_mixtures(vectors, cfg.max_modes, cfg.criterion, cfg.backend, cfg.seed, cfg.reg_covar)
        # the score and what the console draws are small: computed on the CPU (no copy when already there)
        fit = MixtureFit(*(t.cpu() for t in astuple_fit(fit)))
        vectors = vectors.cpu()
        d = mode_divergence(fit.means, fit.n)
        var_g = mixture_variance(vectors, fit.labels, fit.weights)
        return UncertaintyBatch(samples.double().cpu(), vectors, fit, d, var_g, d + cfg.alpha * var_g)

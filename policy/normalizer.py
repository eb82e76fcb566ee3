"""Per-dimension min-max normalization to [0, 1], kept as buffers inside the policy.

Observations are normalized over the training data's range (``fit``). Actions are normalized over
fixed, documented bounds (``set_bounds``): the task's workspace for position and the natural
[-1, 1] for the 6D rotation and the gripper, so that the uncertainty probe's radius r, which lives
in this space, means the same distance in every policy and no recorded data can shrink it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

MIN_SPAN = 1e-3  # dimensions that barely vary in the data are shifted, not stretched
WIDEN_SLACK = 1e-6  # relative float32 rounding that ``widen`` does not count as outside the range


class MinMaxNormalizer(nn.Module):
    """``normalize(x) = (x - low) / span`` over the last dimension; span is at least ``MIN_SPAN``."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("low", torch.zeros(dim))
        self.register_buffer("span", torch.ones(dim))

    def fit(self, data: np.ndarray | torch.Tensor) -> MinMaxNormalizer:
        """data: (N, dim) or (N, ..., dim)."""
        x = torch.as_tensor(np.asarray(data), dtype=torch.float32).reshape(-1, self.low.numel())
        if not torch.isfinite(x).all():
            raise ValueError("cannot fit a normalizer to data with NaN or inf")
        lo, hi = x.min(0).values, x.max(0).values
        span = hi - lo
        narrow = span < MIN_SPAN
        self.low.copy_(torch.where(narrow, (lo + hi) / 2 - 0.5 * MIN_SPAN, lo))
        self.span.copy_(torch.where(narrow, torch.full_like(span, MIN_SPAN), span))
        return self

    def widen(self, data: np.ndarray | torch.Tensor) -> int:
        """Extends the range to cover ``data`` (N, dim) or (N, ..., dim) too, and keeps it where it
        already does: a dimension inside the range normalizes exactly as before. Returns how many
        dimensions were widened."""
        x = torch.as_tensor(np.asarray(data), dtype=torch.float32).reshape(-1, self.low.numel())
        if len(x) == 0:
            return 0
        if not torch.isfinite(x).all():
            raise ValueError("cannot widen a normalizer to data with NaN or inf")
        x_min, x_max, high = x.min(0).values, x.max(0).values, self.low + self.span
        # low + span can round below the data's own maximum: that data is inside, not new
        slack = WIDEN_SLACK * torch.maximum(high.abs(), self.low.abs()).clamp_min(1.0)
        grow = (x_min < self.low - slack) | (x_max > high + slack)
        low = torch.where(grow, torch.minimum(self.low, x_min), self.low)
        # only the widened dimensions get a new span: the others keep theirs bit for bit
        self.span.copy_(torch.where(grow, torch.maximum(high, x_max) - low, self.span))
        self.low.copy_(low)
        return int(grow.sum())

    def set_bounds(self, low: np.ndarray, high: np.ndarray) -> MinMaxNormalizer:
        """Fixed bounds: low, high (dim,), high > low everywhere."""
        lo = torch.as_tensor(np.asarray(low, dtype=np.float64), dtype=torch.float32).reshape(-1)
        hi = torch.as_tensor(np.asarray(high, dtype=np.float64), dtype=torch.float32).reshape(-1)
        if lo.shape != self.low.shape or hi.shape != self.low.shape:
            raise ValueError(f"bounds must have {self.low.numel()} values, got {lo.numel()} and {hi.numel()}")
        if not (torch.isfinite(lo).all() and torch.isfinite(hi).all() and (hi > lo).all()):
            raise ValueError("bounds need finite low < high in every dimension")
        self.low.copy_(lo)
        self.span.copy_(hi - lo)
        return self

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """On ``x``'s device (the statistics follow it: a policy on CUDA normalizes CPU tensors too)."""
        return (x - self.low.to(x.device)) / self.span.to(x.device)

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.span.to(x.device) + self.low.to(x.device)

    def stats(self) -> dict[str, list[float]]:
        return {"min": self.low.tolist(), "max": (self.low + self.span).tolist()}

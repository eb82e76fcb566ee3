"""Per-dimension min-max normalization to [0, 1], kept as buffers inside the policy."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

MIN_SPAN = 1e-3  # dimensions that barely vary in the data are shifted, not stretched


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

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.low) / self.span

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.span + self.low

    def stats(self) -> dict[str, list[float]]:
        return {"min": self.low.tolist(), "max": (self.low + self.span).tolist()}

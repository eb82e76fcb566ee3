"""Mini-batches that mix two datasets in a fixed proportion: fine-tuning's takeover and pretraining data.

The paper fine-tunes on the operators' takeover pairs with half of every mini-batch drawn from the
takeover set and half from the pretraining set, so that the policy learns the corrections without
forgetting what it could do. ``MixedSampler`` draws the indices of one such batch over the two sets
concatenated (the takeover set first); ``train_policy(..., sampler=...)`` uses it in place of its
uniform draw.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class MixedSampler:
    """first: rows of the first set (indices [0, first)); second: rows of the second (indices [first,
    first + second)); ratio: the share of each batch drawn from the first set, exactly
    ``round(ratio * batch)`` rows (with replacement, uniformly within each set)."""

    first: int
    second: int
    ratio: float = 0.5

    def __post_init__(self) -> None:
        if not (0.0 <= self.ratio <= 1.0):
            raise ValueError(f"ratio must be in [0, 1], got {self.ratio!r}")
        if self.first < 0 or self.second < 0:
            raise ValueError(f"set sizes must be >= 0, got {self.first} and {self.second}")
        if self.ratio > 0 and self.first == 0:
            raise ValueError("the first set is empty but ratio asks for some of it in every batch")
        if self.ratio < 1 and self.second == 0:
            raise ValueError("the second set is empty but ratio asks for some of it in every batch")

    def split(self, batch: int) -> tuple[int, int]:
        """(rows from the first set, rows from the second) in a batch of ``batch``."""
        a = round(self.ratio * batch)
        return a, batch - a

    def __call__(self, batch: int, generator: torch.Generator) -> torch.Tensor:
        """(batch,) int64 indices into the concatenated sets: the first set's rows first."""
        a, b = self.split(batch)
        first = torch.randint(0, max(self.first, 1), (a,), generator=generator)
        second = self.first + torch.randint(0, max(self.second, 1), (b,), generator=generator)
        return torch.cat([first, second])

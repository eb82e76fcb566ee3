"""DDPM noise schedule, forward noising and DDIM sampling steps.

Notation follows the paper: ``k`` is the diffusion step (0 = clean data,
``K - 1`` = almost pure noise), ``x_k`` an action chunk at step ``k``, and
``eps`` the noise that the network predicts. All tensors are in the policy's
normalized action space.

Shapes: ``x`` and ``eps`` are ``(..., C, D)`` action chunks (C chunk length,
D action dimensions); ``k`` is an integer tensor broadcastable to ``x.shape[:-2]``.
"""

from __future__ import annotations

import math

import torch


def squared_cosine_betas(num_steps: int, max_beta: float = 0.999) -> torch.Tensor:
    """Betas of the squared-cosine schedule (Nichol & Dhariwal 2021), shape ``(num_steps,)``."""

    def alpha_bar(t: float) -> float:
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = [min(1 - alpha_bar((i + 1) / num_steps) / alpha_bar(i / num_steps), max_beta) for i in range(num_steps)]
    return torch.tensor(betas, dtype=torch.float64)


class NoiseSchedule:
    """ε-prediction DDPM schedule with DDIM (η = 0) sampling.

    ``alphas_cumprod[k]`` is ᾱ_k; ``x_k = sqrt(ᾱ_k) x_0 + sqrt(1 - ᾱ_k) eps``.
    """

    def __init__(self, num_train_steps: int = 100, clip_range: tuple[float, float] | None = None) -> None:
        if num_train_steps < 2:
            raise ValueError(f"num_train_steps must be >= 2, got {num_train_steps}")
        self.num_train_steps = num_train_steps
        betas = squared_cosine_betas(num_train_steps)
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0).float()
        self.clip_range = clip_range

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """Forward process q(x_k | x_0). x0, noise: (B, C, D); k: (B,) long. Returns x_k (B, C, D)."""
        a = self.alphas_cumprod.to(x0.device)[k].view(-1, *([1] * (x0.dim() - 1)))
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    def ddim_timesteps(self, num_inference_steps: int) -> list[int]:
        """Descending diffusion steps visited by DDIM, e.g. 10 of 100 -> [90, 80, ..., 0]."""
        if not 1 <= num_inference_steps <= self.num_train_steps:
            raise ValueError(f"num_inference_steps must be in [1, {self.num_train_steps}], got {num_inference_steps}")
        stride = self.num_train_steps // num_inference_steps
        return [i * stride for i in range(num_inference_steps)][::-1]

    def predict_x0(self, x_k: torch.Tensor, eps: torch.Tensor, k: int) -> torch.Tensor:
        """x̂_0 = (x_k - sqrt(1 - ᾱ_k) eps) / sqrt(ᾱ_k), clipped to ``clip_range`` if set. Shapes (..., C, D)."""
        a = float(self.alphas_cumprod[k])
        x0 = (x_k - math.sqrt(1 - a) * eps) / math.sqrt(a)
        if self.clip_range is not None:
            x0 = x0.clamp(*self.clip_range)
        return x0

    def ddim_step(self, x_k: torch.Tensor, eps: torch.Tensor, k: int, k_prev: int) -> torch.Tensor:
        """Deterministic DDIM update x_k -> x_{k_prev} (k_prev < 0 means "to clean data"). Shapes (..., C, D)."""
        x0 = self.predict_x0(x_k, eps, k)
        if k_prev < 0:
            return x0
        a_prev = float(self.alphas_cumprod[k_prev])
        # re-derive eps from the (possibly clipped) x0 so the update stays consistent
        a = float(self.alphas_cumprod[k])
        eps = (x_k - math.sqrt(a) * x0) / math.sqrt(1 - a)
        return math.sqrt(a_prev) * x0 + math.sqrt(1 - a_prev) * eps

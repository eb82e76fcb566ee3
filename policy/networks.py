"""Noise-prediction networks ε_θ(o, a_k, k).

Both networks take

- ``x``: ``(B, M, C, D)`` noisy action chunks, ``M`` samples per robot (1 when
  training or sampling actions, S when the uncertainty metric probes the field);
- ``k``: ``(B,)`` diffusion steps;
- ``obs``: ``(B, H * obs_dim)`` flattened normalized observation history,

and return ``(B, M, C, D)`` predicted noise. The observation and step
conditioning (FiLM scale and bias) is computed once per robot and broadcast over
the ``M`` samples, which is what makes probing the field cheap.

``ConditionalUnet1D`` is the 1D temporal U-Net of Chi et al. (Diffusion Policy)
with FiLM conditioning; down/up-sampling is used only where the chunk length
allows it, so chunk 1 (the paper's simulated tasks) and chunk 8 both work.
``FilmMLP`` is a small MLP variant for tests.

Chi et al. use Mish; our default is SiLU, which trains as well here and costs a
fifth of Mish on CPU, where the uncertainty probe evaluates 128 samples per robot.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        """k: (B,) -> (B, dim)."""
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=k.device) * -(math.log(10000) / (half - 1)))
        arg = k.float()[:, None] * freqs[None, :]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class _Conv1d(nn.Conv1d):
    """Conv1d with an exact fast path for length-1 sequences (only the centre tap sees data)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ks = self.kernel_size[0]
        if x.shape[-1] == 1 and self.stride[0] == 1 and self.padding[0] == ks // 2:
            return F.linear(x[..., 0], self.weight[:, :, ks // 2], self.bias).unsqueeze(-1)
        return super().forward(x)


class _GroupNorm(nn.GroupNorm):
    """GroupNorm with an exact fast path for length-1 sequences: the group statistics are a layer norm
    over each group's channels (PyTorch's CPU group norm is slow on (N, C, 1) inputs)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != 1:
            return super().forward(x)
        n, c = x.shape[0], x.shape[1]
        h = F.layer_norm(x.view(n, self.num_groups, c // self.num_groups), (c // self.num_groups,), eps=self.eps)
        h = h.view(n, c)
        if self.affine:
            h = torch.addcmul(self.bias, h, self.weight)
        return h.unsqueeze(-1)


ACTIVATIONS = {"mish": nn.Mish, "silu": nn.SiLU}


class _Conv1dBlock(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int, groups: int, act: str) -> None:
        super().__init__(
            _Conv1d(c_in, c_out, kernel, padding=kernel // 2), _GroupNorm(groups, c_out), ACTIVATIONS[act]()
        )


class _FilmResBlock(nn.Module):
    """Two conv blocks; FiLM (per-channel scale and bias from the conditioning) after the first."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel: int, groups: int, act: str) -> None:
        super().__init__()
        self.block1 = _Conv1dBlock(c_in, c_out, kernel, groups, act)
        self.block2 = _Conv1dBlock(c_out, c_out, kernel, groups, act)
        self.film = nn.Sequential(ACTIVATIONS[act](), nn.Linear(cond_dim, 2 * c_out))
        self.residual = _Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.c_out = c_out

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x: (B*M, c_in, C); cond: (B, cond_dim) -> (B*M, c_out, C)."""
        out = self.block1(x)
        b = cond.shape[0]
        scale, bias = self.film(cond).view(b, 1, 2, self.c_out, 1).unbind(2)
        out = (out.view(b, -1, self.c_out, out.shape[-1]) * scale + bias).view_as(out)
        return self.block2(out) + self.residual(x)


def _step_encoder(dim: int) -> nn.Module:
    return nn.Sequential(SinusoidalPosEmb(dim), nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))


class ConditionalUnet1D(nn.Module):
    def __init__(
        self,
        action_dim: int,
        horizon: int,
        obs_cond_dim: int,
        down_dims: tuple[int, ...] = (64, 128),
        kernel_size: int = 5,
        n_groups: int = 8,
        step_embed_dim: int = 64,
        activation: str = "mish",
    ) -> None:
        super().__init__()
        self.step_encoder = _step_encoder(step_embed_dim)
        cond_dim = step_embed_dim + obs_cond_dim
        dims = [action_dim, *down_dims]
        in_out = list(zip(dims[:-1], dims[1:], strict=True))
        levels = len(in_out)
        # level i halves the length after its blocks when the length is still even
        resample = [horizon % (2 ** (i + 1)) == 0 for i in range(levels - 1)]

        def block(a: int, b: int) -> _FilmResBlock:
            return _FilmResBlock(a, b, cond_dim, kernel_size, n_groups, activation)

        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(in_out):
            sample = nn.Conv1d(b, b, 3, 2, 1) if i < levels - 1 and resample[i] else nn.Identity()
            self.down.append(nn.ModuleList([block(a, b), block(b, b), sample]))
        mid = down_dims[-1]
        self.mid = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.up = nn.ModuleList()
        for j, (a, b) in enumerate(reversed(in_out[1:])):
            level = levels - 2 - j
            sample = nn.ConvTranspose1d(a, a, 4, 2, 1) if resample[level] else nn.Identity()
            self.up.append(nn.ModuleList([block(2 * b, a), block(a, a), sample]))
        self.final = nn.Sequential(
            _Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups, activation),
            _Conv1d(down_dims[0], action_dim, 1),
        )

    def forward(self, x: torch.Tensor, k: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        b, m, c, d = x.shape
        cond = torch.cat([self.step_encoder(k), obs], dim=-1)
        h = x.reshape(b * m, c, d).transpose(1, 2)  # (B*M, D, C)
        skips = []
        for res1, res2, down in self.down:
            h = res2(res1(h, cond), cond)
            skips.append(h)
            h = down(h)
        for res in self.mid:
            h = res(h, cond)
        for res1, res2, up in self.up:  # as in Chi et al., the shallowest skip is unused
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(res2(res1(h, cond), cond))
        return self.final(h).transpose(1, 2).reshape(b, m, c, d)


class FilmMLP(nn.Module):
    """Residual MLP over the flattened chunk, FiLM-conditioned on observation and step."""

    def __init__(
        self,
        action_dim: int,
        horizon: int,
        obs_cond_dim: int,
        hidden: int = 128,
        layers: int = 2,
        step_embed_dim: int = 32,
    ) -> None:
        super().__init__()
        self.step_encoder = _step_encoder(step_embed_dim)
        cond_dim = step_embed_dim + obs_cond_dim
        self.inp = nn.Linear(action_dim * horizon, hidden)
        self.layers = nn.ModuleList([nn.Linear(hidden, hidden) for _ in range(layers)])
        self.films = nn.ModuleList([nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * hidden)) for _ in range(layers)])
        self.out = nn.Linear(hidden, action_dim * horizon)
        self.hidden = hidden

    def forward(self, x: torch.Tensor, k: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        b, m, c, d = x.shape
        cond = torch.cat([self.step_encoder(k), obs], dim=-1)
        h = self.inp(x.reshape(b, m, c * d))
        for layer, film in zip(self.layers, self.films, strict=True):
            scale, bias = film(cond).view(b, 1, 2, self.hidden).unbind(2)
            h = h + F.mish(layer(h) * scale + bias)
        return self.out(F.mish(h)).view(b, m, c, d)

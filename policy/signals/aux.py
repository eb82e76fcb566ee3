"""Auxiliary networks of the baselines and their offline training loops.

- ``EnsembleMLP``: E independent MLPs evaluated in one batched pass (einsum over stacked weights);
- ``Transitions``: (o, a, r, o', a', done) from recorded episodes, reward 1 on the final step of a
  successful episode, with the recorded next action (SARSA-style: on the policy's own rollouts that
  is the deployed policy's action, so the critics value the policy we run);
- ``train_bc_ensemble``: behaviour cloning with a bootstrap resample per member (ThriftyDAgger);
- ``train_q``: TD learning of E critics with target networks, optionally with the conservative
  (CQL(H)) penalty and sigmoid outputs (twin-Q success probability for ThriftyDAgger).

Inputs are the policy's normalized observation history (flattened) and normalized actions.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import StepSet


class EnsembleLinear(nn.Module):
    def __init__(self, members: int, d_in: int, d_out: int) -> None:
        super().__init__()
        bound = 1 / math.sqrt(d_in)
        self.weight = nn.Parameter(torch.empty(members, d_in, d_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(members, 1, d_out).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (E, B, d_in) -> (E, B, d_out)."""
        return torch.baddbmm(self.bias, x, self.weight)


class EnsembleMLP(nn.Module):
    """E MLPs d_in -> hidden... -> d_out; ``forward`` takes (B, d_in) (shared) or (E, B, d_in)."""

    def __init__(self, members: int, d_in: int, d_out: int, hidden: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        dims = [d_in, *hidden, d_out]
        self.members = members
        self.layers = nn.ModuleList(EnsembleLinear(members, a, b) for a, b in zip(dims[:-1], dims[1:], strict=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 2:
            x = x.expand(self.members, *x.shape)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = torch.nn.functional.silu(x)
        return x


def features(policy: DiffusionPolicy, obs: torch.Tensor) -> torch.Tensor:
    """(B, H, obs_dim) raw -> (B, H*obs_dim) normalized, flattened."""
    return policy.normalize_obs(obs).flatten(1)


def norm_action(policy: DiffusionPolicy, action: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(..., 10) raw -> normalized."""
    return policy.normalize_action(torch.as_tensor(action, dtype=torch.float32))


@dataclass
class Transitions:
    obs: torch.Tensor  # (M, F)
    action: torch.Tensor  # (M, 10) normalized executed action
    reward: torch.Tensor  # (M,)
    next_obs: torch.Tensor
    next_action: torch.Tensor
    done: torch.Tensor  # (M,) 1.0 at an episode's last step

    def __len__(self) -> int:
        return self.obs.shape[0]

    @classmethod
    def from_steps(cls, policy: DiffusionPolicy, *sets: StepSet) -> Transitions:
        parts = []
        for steps in sets:
            nxt = np.arange(len(steps))
            for rows in steps.episodes():
                nxt[rows[:-1]] = rows[1:]
                nxt[rows[-1]] = rows[-1]
            done = steps.t == steps.last
            reward = (done & steps.success).astype(np.float32)
            obs = features(policy, steps.obs)
            act = norm_action(policy, steps.action[:, 0])
            parts.append(
                (obs, act, torch.as_tensor(reward), obs[nxt], act[nxt], torch.as_tensor(done, dtype=torch.float32))
            )
        return cls(*(torch.cat(cols) for cols in zip(*parts, strict=True)))


def _adam(params, lr: float) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=lr)


def train_bc_ensemble(
    model: EnsembleMLP,
    obs: torch.Tensor,
    target: torch.Tensor,
    steps: int,
    seed: int,
    batch: int = 256,
    lr: float = 1e-3,
    progress: bool = True,
) -> list[float]:
    """obs (M, F), target (M, T) normalized; each member trains on its own bootstrap resample."""
    g = torch.Generator().manual_seed(seed)
    m, e = obs.shape[0], model.members
    boot = torch.randint(0, m, (e, m), generator=g)  # member i sees rows boot[i]
    opt = _adam(model.parameters(), lr)
    losses = []
    bar = tqdm(range(steps), desc="train ensemble", disable=not progress, unit="step")
    try:
        for _ in bar:
            pick = torch.randint(0, m, (e, batch), generator=g)
            rows = torch.gather(boot, 1, pick)  # (E, batch)
            loss = ((model(obs[rows]) - target[rows]) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            if len(losses) % 100 == 0:
                bar.set_postfix(loss=f"{np.mean(losses[-100:]):.5f}")
    finally:
        bar.close()
    return losses


@dataclass(frozen=True)
class QTraining:
    gamma: float = 0.995
    lr: float = 3e-4
    batch: int = 256
    polyak: float = 0.995
    sigmoid: bool = False  # outputs are probabilities (ThriftyDAgger's success Q)
    min_target: bool = False  # target = min over members (twin Q) instead of each member's own
    cql_alpha: float = 0.0  # conservative penalty weight (0: plain TD)
    cql_actions: int = 10
    positive_fraction: float = 0.1  # share of reward-1 transitions per batch (sparse success reward)


def q_values(model: EnsembleMLP, obs: torch.Tensor, action: torch.Tensor, sigmoid: bool) -> torch.Tensor:
    """(B, F), (B, 10) -> (E, B)."""
    out = model(torch.cat([obs, action], dim=-1))[..., 0]
    return torch.sigmoid(out) if sigmoid else out


def train_q(
    model: EnsembleMLP, data: Transitions, steps: int, cfg: QTraining, seed: int, progress: bool = True
) -> list[float]:
    g = torch.Generator().manual_seed(seed)
    target_net = copy.deepcopy(model).requires_grad_(False)
    opt = _adam(model.parameters(), cfg.lr)
    positives = torch.nonzero(data.reward > 0).flatten()
    n_pos = min(len(positives), int(round(cfg.batch * cfg.positive_fraction))) if len(positives) else 0
    losses = []
    bar = tqdm(range(steps), desc="train critic", disable=not progress, unit="step")
    try:
        for _ in bar:
            rows = torch.randint(0, len(data), (cfg.batch - n_pos,), generator=g)
            if n_pos:
                rows = torch.cat([rows, positives[torch.randint(0, len(positives), (n_pos,), generator=g)]])
            o, a, r = data.obs[rows], data.action[rows], data.reward[rows]
            with torch.no_grad():
                nq = q_values(target_net, data.next_obs[rows], data.next_action[rows], cfg.sigmoid)  # (E, B)
                if cfg.min_target:
                    nq = nq.min(dim=0, keepdim=True).values.expand_as(nq)
                target = r + cfg.gamma * (1 - data.done[rows]) * nq
            q = q_values(model, o, a, cfg.sigmoid)
            loss = ((q - target) ** 2).mean()
            if cfg.cql_alpha > 0:
                n, b = cfg.cql_actions, len(rows)
                rand = torch.rand((n * b, a.shape[1]), generator=g)
                q_rand = q_values(model, o.repeat(n, 1), rand, cfg.sigmoid).view(-1, n, b).transpose(0, 1)  # (N, E, B)
                # CQL(H): push down a soft maximum over actions, push up the data's actions
                penalty = torch.logsumexp(torch.cat([q_rand, q[None]], dim=0), dim=0) - q
                loss = loss + cfg.cql_alpha * penalty.mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():
                for pt, p in zip(target_net.parameters(), model.parameters(), strict=True):
                    pt.lerp_(p, 1 - cfg.polyak)
            losses.append(float(loss.detach()))
            if len(losses) % 100 == 0:
                bar.set_postfix(loss=f"{np.mean(losses[-100:]):.5f}")
    finally:
        bar.close()
    return losses

"""``hitl bench signals``: what each signal costs per robot-step, measured.

For a batch of B recorded rollout states, each signal's ``score`` is timed (median of repeats after
a warm-up) with the policy's action for the step supplied, as in the fleet loop where it is sampled
anyway. Forward hooks count what ran: rows through the policy's noise-prediction network (one row
= one ε_θ evaluation of one action sample) and rows through auxiliary networks (x members).
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from bench.harness import timed
from policy.diffusion_policy import DiffusionPolicy
from policy.signals.aux import EnsembleMLP
from policy.signals.base import AssistanceSignal, SignalInput, StepSet


class _Counter:
    def __init__(self) -> None:
        self.rows = 0
        self.calls = 0

    def policy_hook(self, module: nn.Module, args: tuple) -> None:
        x = args[0]
        self.rows += x.shape[0] * x.shape[1]
        self.calls += 1

    def aux_hook(self, module: nn.Module, args: tuple) -> None:
        x = args[0]
        self.rows += module.members * (x.shape[-2] if x.dim() == 3 else x.shape[0])
        self.calls += 1


def _aux_modules(signal: AssistanceSignal) -> list[EnsembleMLP]:
    return [m for m in vars(signal).values() if isinstance(m, EnsembleMLP)]


def _input(policy: DiffusionPolicy, steps: StepSet, b: int) -> SignalInput:
    obs = torch.as_tensor(steps.obs[:b])
    with torch.no_grad():
        action = policy.predict_action_chunk(obs)
    return SignalInput(obs, torch.as_tensor(steps.current[:b]), np.arange(b), action=action)


def _measure(signal: AssistanceSignal, batch: SignalInput, repeats: int) -> dict:
    policy_count, aux_count = _Counter(), _Counter()
    handles = [signal.policy.net.register_forward_pre_hook(policy_count.policy_hook)]
    handles += [m.register_forward_pre_hook(aux_count.aux_hook) for m in _aux_modules(signal)]
    b = len(batch)
    try:
        signal.reset()
        with torch.no_grad():
            signal.score(batch)  # warm-up (and, for stateful signals, a previous step)
            policy_count.rows = policy_count.calls = aux_count.rows = aux_count.calls = 0
            times = []
            for _ in range(repeats):
                t = time.perf_counter()
                signal.score(batch)
                times.append(time.perf_counter() - t)
    finally:
        for h in handles:
            h.remove()
    return {
        "ms_per_robot_step": float(np.median(times)) * 1e3 / b,
        "policy_net_rows_per_robot_step": policy_count.rows / repeats / b,
        "policy_net_calls_per_step": policy_count.calls / repeats,
        "aux_net_rows_per_robot_step": aux_count.rows / repeats / b,
    }


def bench_signals(
    signals: dict[str, AssistanceSignal],
    steps: StepSet,
    fleet_size: int,
    repeats: int = 5,
    progress: bool = True,
) -> dict:
    """Per signal: ms and forward passes per robot-step at ``fleet_size``; DDIM sampling as reference."""
    rng = np.random.default_rng(0)
    steps = steps.take(rng.permutation(len(steps))[: max(fleet_size, 1)])
    b = min(fleet_size, len(steps))
    rows: dict[str, dict] = {}
    ddim: dict[str, float] = {}
    bar = tqdm(signals.items(), desc="bench signals", disable=not progress)
    for name, signal in bar:
        bar.set_postfix(signal=name)
        policy = signal.policy
        batch = _input(policy, steps, b)
        key = id(policy)
        if key not in ddim:
            ddim[key] = _measure_ddim(policy, batch.obs, repeats)
        rows[name] = _measure(signal, batch, repeats) | {"ddim_ms_per_robot_step": ddim[key]}
    base = rows.get("denoising")
    if base:
        for r in rows.values():
            r["cost_over_denoising"] = r["ms_per_robot_step"] / base["ms_per_robot_step"]
    return {"fleet_size": b, "repeats": repeats, "signals": rows}


def _measure_ddim(policy: DiffusionPolicy, obs: torch.Tensor, repeats: int) -> float:
    with torch.no_grad():
        return timed(lambda: policy.predict_action_chunk(obs), repeats) * 1e3 / obs.shape[0]

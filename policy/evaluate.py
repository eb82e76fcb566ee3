"""Autonomous policy rollouts on the simulated tasks, with per-step uncertainty.

``rollout_policy`` runs episodes in waves of ``n_envs`` simulated robots that
step in lockstep (``policy.lockstep``) through the fleet's ``Controller``: the
policy and the uncertainty are called once per control step for the whole
wave, and chunks are queued exactly as the fleet serves them. ``rollout_check`` measures a
calibrated threshold on such rollouts (the share of steps above it). What the uncertainty figures
keep of each step (its field, the probe's inputs) is the lab's (``lab.fields``, through ``on_step``).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from policy.calibrate import FLAG_SHARE
from policy.controller import Controller, RobotStep
from policy.diffusion_policy import DiffusionPolicy
from policy.lockstep import StepHook, run_lockstep
from policy.signals.base import AssistanceSignal
from policy.signals.sampling import DenoisingConfig, DenoisingSignal
from policy.uncertainty import UncertaintyConfig
from sim.env import Task
from sim.registry import make_task


@dataclass
class PolicyEpisode:
    task: str
    seed: int
    success: bool
    steps: int
    info: dict
    uncertainty: list[float] = field(default_factory=list)
    modes: list[int] = field(default_factory=list)
    trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list
    )  # (obs history, current, action)
    signal_scores: list[dict[str, float]] = field(default_factory=list)  # per step, each shadow signal's score

    def summary(self) -> dict:
        u = np.asarray(self.uncertainty)
        out = {"seed": self.seed, "success": self.success, "steps": self.steps, **self.info}
        if len(u):
            out["uncertainty"] = {
                "mean": float(u.mean()),
                "max": float(u.max()),
                "argmax_step": int(u.argmax()),
                "p95": float(np.quantile(u, 0.95)),
            }
        return out


def rollout_policy(
    policy: DiffusionPolicy,
    task_name: str,
    seeds: list[int],
    n_envs: int = 4,
    uncertainty: UncertaintyConfig | None = None,
    progress: bool = True,
    trace: bool = False,
    seed: int = 0,
    signals: Mapping[str, AssistanceSignal] | None = None,
    on_step: StepHook | None = None,
) -> tuple[list[PolicyEpisode], dict]:
    """Runs one autonomous episode per seed through the controller; an episode ends at success or
    at the task horizon. ``uncertainty``: score the denoising metric at every step with these
    settings (the fleet's shadow scoring); ``trace`` keeps every step's observation history (as the policy
    saw it: ``RobotStep.seen``), probe
    centre and executed action; ``seed``: the controller's sampling seed; ``signals``: scored in the
    shadow at every step (none asks), their scores kept in ``signal_scores``; ``on_step``: told every
    robot's step before it is applied (episode index, task, the decision). Returns (episodes, timing)."""
    shadow = dict(signals or {})
    signals = dict(shadow)
    if uncertainty is not None:
        signals["denoising"] = DenoisingSignal(policy, DenoisingConfig.from_uncertainty(uncertainty))
    controller = Controller(policy, signals, None, make_task(task_name).action_space, seed=seed)
    episodes = [PolicyEpisode(task_name, s, False, 0, {}) for s in seeds]

    def record(rid: int, task: Task, step: RobotStep) -> None:
        ep = episodes[rid]
        if step.uncertainty is not None:
            ep.uncertainty.append(step.uncertainty.U)
            ep.modes.append(step.uncertainty.n)
        if trace:
            ep.trace.append((step.seen, step.current, step.action.astype(np.float32)))
        if shadow and step.scores:
            ep.signal_scores.append({name: step.scores[name] for name in shadow})
        if on_step is not None:
            on_step(rid, task, step)

    start = time.perf_counter()
    outcomes = run_lockstep(
        controller, task_name, seeds, n_envs, record, progress=progress, desc=f"rollout {task_name}"
    )
    for ep, out in zip(episodes, outcomes, strict=True):
        ep.success, ep.steps, ep.info = out.success, out.steps, out.info
    return episodes, {"seconds": time.perf_counter() - start}


def summarize(episodes: list[PolicyEpisode]) -> dict:
    steps = np.array([e.steps for e in episodes])
    u_all = np.concatenate([e.uncertainty for e in episodes]) if episodes and episodes[0].uncertainty else None
    out = {
        "episodes": len(episodes),
        "success_rate": float(np.mean([e.success for e in episodes])) if episodes else 0.0,
        "successes": int(sum(e.success for e in episodes)),
        "steps": {"mean": float(steps.mean()), "min": int(steps.min()), "max": int(steps.max())} if episodes else {},
    }
    if u_all is not None and len(u_all):
        out["uncertainty"] = {
            "mean": float(u_all.mean()),
            "median": float(np.median(u_all)),
            "p95": float(np.quantile(u_all, 0.95)),
            "max": float(u_all.max()),
            "modes_histogram": {
                str(k): int(v)
                for k, v in zip(
                    *np.unique(np.concatenate([e.modes for e in episodes]), return_counts=True), strict=True
                )
            },
        }
    return out


def rollout_check(
    policy: DiffusionPolicy,
    task: str,
    threshold: float,
    config: UncertaintyConfig,
    episodes: int = 10,
    seed: int = 3000,
    n_envs: int = 5,
    progress: bool = True,
) -> dict:
    """The share of steps above ``threshold`` on autonomous rollouts of ``task`` (seeds ``seed``..),
    through the one controller with the same uncertainty settings; ``flagged`` when over FLAG_SHARE.
    Only episodes' steps count; success is reported beside it (a policy that fails its own task
    visits states the validation set lacks)."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    eps, _ = rollout_policy(
        policy,
        task,
        list(range(seed, seed + episodes)),
        n_envs=min(n_envs, episodes),
        uncertainty=config,
        progress=progress,
    )
    u = np.concatenate([e.uncertainty for e in eps])
    share = float(np.mean(u > threshold))
    return {
        "task": task,
        "episodes": episodes,
        "seeds": [seed, seed + episodes - 1],
        "successes": int(sum(e.success for e in eps)),
        "steps": int(len(u)),
        "share_above": share,
        "flag_share": FLAG_SHARE,
        "flagged": share > FLAG_SHARE,
        "u_median": float(np.median(u)),
    }

"""Autonomous policy rollouts on the simulated tasks, with per-step uncertainty.

``rollout_policy`` runs episodes in waves of ``n_envs`` simulated robots that
step in lockstep, so the policy and the uncertainty estimator are called once
per control step for the whole wave, as they are for a fleet.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from policy.uncertainty import UncertaintyEstimator, UncertaintyResult
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
    fields: list[UncertaintyResult] = field(default_factory=list)  # kept only when asked
    context: list[float] = field(default_factory=list)  # task-specific signal per step (see CONTEXT)
    probe_inputs: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (obs history, centre)
    trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list
    )  # (obs history, current, action)

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


def _lift_context(task: Task) -> float:
    return float(np.linalg.norm(task.ee_pose()[0] - task.privileged()["grasp_point"]))


def _cup_context(task: Task) -> float:
    s = task.privileged()
    return float(np.linalg.norm(s["green_pos"][:2] - s["red_pos"][:2]))


def _drawer_context(task: Task) -> float:
    return float(np.min(np.linalg.norm(task.privileged()["handles"] - task.ee_pose()[0], axis=1)))


# what to plot under the uncertainty timeline: (axis label, function of the task state)
CONTEXT = {
    "lift": ("gripper to object grasp point (m)", _lift_context),
    "cup-stack": ("green to red cup, horizontal (m)", _cup_context),
    "open-drawer": ("gripper to nearest handle (m)", _drawer_context),
}


def context_for(task_name: str):
    return CONTEXT["lift" if task_name.startswith("lift") else task_name]


def _run_wave(
    policy: DiffusionPolicy,
    tasks: list[Task],
    seeds: list[int],
    estimator: UncertaintyEstimator | None,
    keep_fields: bool,
    bar: tqdm,
    trace: bool = False,
) -> list[PolicyEpisode]:
    n = len(seeds)
    obs = np.stack([t.reset(s) for t, s in zip(tasks, seeds, strict=True)])
    policy.reset(seed=seeds[0])
    episodes = [PolicyEpisode(tasks[i].name, seeds[i], False, 0, {}) for i in range(n)]
    active = np.ones(n, dtype=bool)
    while active.any():
        action = policy.select_action(torch.as_tensor(obs, dtype=torch.float32)).numpy().astype(np.float64)
        history = policy.observation_history()
        if estimator is not None or trace:
            current = np.stack([t.hold_action() for t in tasks[:n]]).astype(np.float32)
        if estimator is not None:
            center = policy.normalize_action(torch.as_tensor(current))
            batch = estimator(policy.noise_prediction, history, center, chunk=policy.config.action_horizon)
        for i in np.flatnonzero(active):
            ep = episodes[i]
            if estimator is not None:
                ep.uncertainty.append(float(batch.U[i]))
                ep.modes.append(int(batch.fit.n[i]))
                if keep_fields:
                    ep.fields.append(batch.robot(i))
                    ep.probe_inputs.append((history[i].numpy(), center[i].numpy()))
            if keep_fields:
                ep.context.append(context_for(tasks[i].name)[1](tasks[i]))
            if trace:
                ep.trace.append((history[i].numpy(), current[i], action[i].astype(np.float32)))
            result = tasks[i].step(action[i])
            obs[i] = result.obs
            ep.steps = result.t
            if result.success or result.done:
                ep.success = bool(result.success)
                ep.info = tasks[i].episode_info()
                active[i] = False
                bar.update(1)
    return episodes


def rollout_policy(
    policy: DiffusionPolicy,
    task_name: str,
    seeds: list[int],
    n_envs: int = 4,
    estimator: UncertaintyEstimator | None = None,
    keep_fields: bool = False,
    progress: bool = True,
    trace: bool = False,
) -> tuple[list[PolicyEpisode], dict]:
    """Runs one autonomous episode per seed; an episode ends at success or at the task horizon.

    ``trace`` keeps every step's observation history, current pose action and executed action.
    Returns (episodes, timing).
    """
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs}")
    tasks = [make_task(task_name) for _ in range(min(n_envs, len(seeds)))]
    obs_dim = tasks[0].obs_spec.dim
    if obs_dim != policy.config.obs_dim:
        raise ValueError(f"policy expects {policy.config.obs_dim}-dim observations, task {task_name} gives {obs_dim}")
    episodes: list[PolicyEpisode] = []
    start = time.perf_counter()
    bar = tqdm(total=len(seeds), desc=f"rollout {task_name}", disable=not progress, unit="ep")
    try:
        for w in range(0, len(seeds), len(tasks)):
            wave = seeds[w : w + len(tasks)]
            episodes += _run_wave(policy, tasks[: len(wave)], wave, estimator, keep_fields, bar, trace)
    finally:
        bar.close()
        for t in tasks:
            t.close()
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

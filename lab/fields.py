"""Autonomous rollouts that keep what the uncertainty figures and the metric's cost benchmark read:
every step's denoising field, the probe's inputs and a task-specific context (``hitl plot uncertainty``,
``hitl bench uncertainty``, ``bench.figures``). The rollouts are ``policy.evaluate.rollout_policy``'s."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from policy.controller import RobotStep
from policy.diffusion_policy import DiffusionPolicy
from policy.evaluate import PolicyEpisode, rollout_policy
from policy.uncertainty import UncertaintyConfig, UncertaintyResult
from sim.env import Task


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


@dataclass
class FieldEpisode(PolicyEpisode):
    """A ``PolicyEpisode`` with every scored step's field and probe inputs, and every step's context."""

    fields: list[UncertaintyResult] = field(default_factory=list)
    context: list[float] = field(default_factory=list)  # task-specific signal per step (see CONTEXT)
    probe_inputs: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (obs history, centre)


def rollout_fields(
    policy: DiffusionPolicy,
    task_name: str,
    seeds: list[int],
    uncertainty: UncertaintyConfig,
    n_envs: int = 4,
    progress: bool = True,
) -> tuple[list[FieldEpisode], dict]:
    """``rollout_policy`` with the denoising metric scored at every step, each step's field, probe inputs
    (observation history, normalized probe centre) and context kept. Returns (episodes, timing)."""
    kept = [FieldEpisode(task_name, s, False, 0, {}) for s in seeds]

    def keep(rid: int, task: Task, step: RobotStep) -> None:
        ep = kept[rid]
        if step.uncertainty is not None:
            ep.fields.append(step.uncertainty)
            center = policy.normalize_action(torch.as_tensor(step.current)).numpy()
            ep.probe_inputs.append((step.obs, center))
        ep.context.append(context_for(task.name)[1](task))

    episodes, timing = rollout_policy(
        policy, task_name, seeds, n_envs=n_envs, uncertainty=uncertainty, progress=progress, on_step=keep
    )
    for ep, out in zip(episodes, kept, strict=True):
        for f in dataclasses.fields(PolicyEpisode):
            setattr(out, f.name, getattr(ep, f.name))
    return kept, timing

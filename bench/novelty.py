"""``hitl report novelty``: how far each task's observations lie outside a policy's training range.

This is the input that ``choice-stall`` decides on (``policy/signals/choice_stall.py``): a robot's scene
is new once its observation novelty (``spread``'s novelty term, ``observation_novelty``) passes the
signal's ``novelty_gate``. The policy rolls out autonomously on each task through the one controller
(seeded; ``policy.signal_data.policy_rollouts``, cached next to the policy), and every visited state's
novelty is summarised per task: its least and greatest value, and the share of states over the gate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from policy.diffusion_policy import DiffusionPolicy
from policy.signal_data import policy_rollouts
from policy.signals.spread import observation_novelty


@dataclass(frozen=True)
class TaskNovelty:
    episodes: int
    states: int
    success_rate: float
    min: float
    median: float
    max: float
    share_over_gate: float


@dataclass(frozen=True)
class NoveltyReport:
    policy: str
    seeds: list[int]
    gate: float
    tasks: dict[str, TaskNovelty]

    def to_dict(self) -> dict:
        return {**asdict(self), "tasks": {k: asdict(v) for k, v in self.tasks.items()}}

    def markdown(self) -> str:
        lines = [
            f"Observation novelty of `{self.policy}`'s autonomous rollouts, seeds {self.seeds[0]}–{self.seeds[-1]}"
            f" (gate {self.gate:g})",
            "",
            "| task | episodes | success | min | median | max | states over the gate |",
            "|---|---|---|---|---|---|---|",
        ]
        for task, t in self.tasks.items():
            lines.append(
                f"| {task} | {t.episodes} | {t.success_rate:.0%} | {t.min:.4f} | {t.median:.4f} | {t.max:.4f} "
                f"| {t.share_over_gate:.1%} |"
            )
        return "\n".join(lines)


def task_novelty(
    policy: DiffusionPolicy,
    policy_dir: str | Path,
    tasks: list[str],
    episodes: int,
    seed: int,
    gate: float,
    progress: bool = True,
) -> NoveltyReport:
    seeds = list(range(seed, seed + episodes))
    out = {}
    for task in tasks:
        steps = policy_rollouts(policy, policy_dir, task, seeds, progress=progress)
        with torch.no_grad():
            novelty = observation_novelty(policy.normalize_obs(torch.as_tensor(steps.obs))).double().numpy()
        first = np.unique(steps.episode, return_index=True)[1]  # one row per episode
        out[task] = TaskNovelty(
            episodes=len(first),
            states=len(novelty),
            success_rate=float(steps.success[first].mean()),
            min=float(novelty.min()),
            median=float(np.median(novelty)),
            max=float(novelty.max()),
            share_over_gate=float((novelty > gate).mean()),
        )
    return NoveltyReport(str(policy_dir), seeds, gate, out)

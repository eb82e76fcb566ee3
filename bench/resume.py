"""``hitl report resume``: where a policy stops being useful, and whether a few operator steps there let
it finish on its own.

For each takeover step k of a grid, every seed's episode runs on the policy through the one controller
(``lab.assisted.run_assisted``); at its k-th policy step the robot asks once (``AtStep``), the
simulated operator (the task's scripted expert, from the operator view) drives it for ``budget`` steps,
the paper's 4 by default, and the policy finishes alone. The same seeds also run with no takeover. The
policy's sampling noise is seeded per episode, so up to step k a takeover episode is the autonomous one:
the difference at the end is what the operator's steps made.

Per step k and budget the report gives the success rate, the episodes the takeover *rescued* (failed
alone, succeeded with it) and *broke* (the other way round), and how many episodes were still running
at step k (an episode that has already ended never asks). A policy that resumes after a few steps at
the state that matters shows rescues there; one that returns to its own plan shows none at any k.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from lab.assisted import AssistConfig, run_assisted
from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    PerRobot,
    Scores,
    SignalConfig,
    SignalInput,
    TriggerState,
)


@dataclass(frozen=True)
class AtStepConfig(SignalConfig):
    """at: the policy step (from 0, counting the robot's own steps only) on which the robot asks."""

    at: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.at, int) and not isinstance(self.at, bool) and self.at >= 0):
            raise ValueError(f"at must be an integer >= 0, got {self.at!r}")


class AtStep(AssistanceSignal):
    """Asks once per episode, at a set policy step: the probe of this report, not an asking signal."""

    name = "at-step"
    Config = AtStepConfig

    def __init__(self, policy: DiffusionPolicy, config: AtStepConfig | None = None) -> None:
        super().__init__(policy, config)
        self._steps = PerRobot(int)  # policy steps scored so far this episode
        self.calibration = self._calibrate(None, False)

    def reset(self, robot_ids=None) -> None:
        self._steps.reset(self._ids_for(robot_ids))

    def score(self, batch: SignalInput) -> Scores:
        return Scores(np.array([float(self._steps.get(int(r)) == self.config.at) for r in batch.robot_ids]))

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        out = (np.asarray(scores.value) > self.threshold) & ~np.asarray(state.teleop, dtype=bool)
        for j, rid in enumerate(int(r) for r in state.robot_ids):
            if not state.teleop[j]:
                self._steps.set(rid, self._steps.get(rid) + 1)
        return out

    def _calibrate(self, data: CalibrationData | None, progress: bool) -> dict:
        return {
            "threshold": 0.5,
            "quantile": None,
            "samples": 0,
            "source": f"asks once, at policy step {self.config.at}",
        }


@dataclass(frozen=True)
class ResumeCell:
    at: int  # the policy step of the takeover
    budget: int  # operator steps
    reached: int  # episodes still running at that step (the others never asked)
    success_rate: float
    rescued: int  # failed alone, succeeded with the takeover
    broke: int  # succeeded alone, failed with it
    assisted_steps: float  # per episode


@dataclass(frozen=True)
class TaskResume:
    task: str
    policy: str
    seeds: list[int]
    alone: float  # success rate with no takeover
    alone_steps: float  # steps per autonomous episode
    cells: list[ResumeCell]
    resume: str = "restart"  # what the policy saw after the hand-back (``policy.hand_back.RESUME``)


@dataclass(frozen=True)
class ResumeReport:
    tasks: list[TaskResume]

    def to_dict(self) -> dict:
        return {"tasks": [asdict(t) for t in self.tasks]}

    def markdown(self) -> str:
        lines = []
        for t in self.tasks:
            budgets = sorted({c.budget for c in t.cells})
            lines += [
                f"`{t.policy}` on {t.task}, seeds {t.seeds[0]}–{t.seeds[-1]}: alone {t.alone:.0%} "
                f"({t.alone_steps:.0f} steps per episode). One takeover at policy step k, then a hand-back "
                f"that {'keeps the takeover in the history' if t.resume == 'history' else 'restarts the history'}:",
                "",
                "| k | still running | "
                + " | ".join(f"success, {b} operator steps (rescued / broke)" for b in budgets)
                + " |",
                "|---|---|" + "---|" * len(budgets),
            ]
            for at in sorted({c.at for c in t.cells}):
                row = {c.budget: c for c in t.cells if c.at == at}
                reached = next(iter(row.values())).reached
                cols = [f"{row[b].success_rate:.0%} (+{row[b].rescued} / −{row[b].broke})" for b in budgets]
                lines.append(f"| {at} | {reached}/{len(t.seeds)} | " + " | ".join(cols) + " |")
            lines.append("")
        return "\n".join(lines)


def task_resume(
    policy: DiffusionPolicy,
    policy_name: str,
    task: str,
    steps: list[int],
    budgets: list[int],
    episodes: int,
    seed: int,
    n_envs: int = 8,
    progress: bool = True,
    resume: str = "restart",
) -> TaskResume:
    """One report row per (takeover step, budget) on ``episodes`` seeds from ``seed``; ``resume``: what the
    policy sees after the hand-back (``policy.hand_back.RESUME``)."""
    if not steps or not budgets:
        raise ValueError("give at least one takeover step and one budget")
    seeds = list(range(seed, seed + episodes))
    alone, _ = run_assisted(policy, task, seeds, None, config=AssistConfig(n_envs=n_envs), progress=progress)
    ok = np.array([e.success for e in alone])
    cells = []
    for budget in budgets:
        for at in steps:
            driver = AtStep(policy, AtStepConfig(at=at))
            cfg = AssistConfig(hand_back="budgeted", budget=budget, n_envs=n_envs, resume=resume)
            eps, _ = run_assisted(policy, task, seeds, driver, config=cfg, progress=progress)
            won = np.array([e.success for e in eps])
            cells.append(
                ResumeCell(
                    at=at,
                    budget=budget,
                    reached=int(sum(e.events > 0 for e in eps)),
                    success_rate=float(won.mean()),
                    rescued=int((won & ~ok).sum()),
                    broke=int((~won & ok).sum()),
                    assisted_steps=float(np.mean([e.assisted_steps for e in eps])),
                )
            )
    steps = float(np.mean([e.steps for e in alone]))
    return TaskResume(task, policy_name, seeds, float(ok.mean()), steps, cells, resume)


@dataclass(frozen=True)
class PregraspEpisode:
    seed: int
    operator_steps: int  # the operator's steps to the pre-grasp pose
    closed: bool  # the policy closed the gripper after the hand-back
    success: bool  # ... and the episode succeeded (the object lifted) with no further help
    steps_after: int  # the policy's steps from the hand-back to the episode's end


@dataclass(frozen=True)
class TaskPregrasp:
    """Handed back at the pre-grasp pose: the operator placed the open gripper at the grasp, the policy
    is to close and lift alone."""

    task: str
    policy: str
    seeds: list[int]
    alone: float  # success rate with no takeover
    episodes: list[PregraspEpisode]

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else 0.0

    @property
    def closed_rate(self) -> float:
        return float(np.mean([e.closed for e in self.episodes])) if self.episodes else 0.0

    def summary(self) -> dict:
        return {
            "task": self.task,
            "alone": self.alone,
            "closed": self.closed_rate,
            "success_rate": self.success_rate,
            "operator_steps": float(np.mean([e.operator_steps for e in self.episodes])) if self.episodes else 0.0,
        }


@dataclass(frozen=True)
class PregraspReport:
    tasks: list[TaskPregrasp]

    def to_dict(self) -> dict:
        return {"tasks": [{**asdict(t), "summary": t.summary()} for t in self.tasks]}

    def markdown(self) -> str:
        lines = [
            "Handed back at the pre-grasp pose: the operator places the open gripper at the grasp, then the "
            "policy goes on alone.",
            "",
            "| task | policy | episodes | alone | closed after the hand-back | closed and lifted | operator steps |",
            "|---|---|---|---|---|---|---|",
        ]
        for t in self.tasks:
            s = t.summary()
            lines.append(
                f"| {t.task} | `{t.policy}` | {len(t.seeds)} | {t.alone:.0%} | {s['closed']:.0%} | "
                f"{s['success_rate']:.0%} | {s['operator_steps']:.1f} |"
            )
        return "\n".join(lines) + "\n"


def task_pregrasp(
    policy: DiffusionPolicy,
    policy_name: str,
    task: str,
    episodes: int,
    seed: int,
    n_envs: int = 8,
    progress: bool = True,
) -> TaskPregrasp:
    """``episodes`` seeds from ``seed``, each run twice through the one controller: alone, and with the robot
    asking at its first step, the simulated operator driving it to the pre-grasp pose (``Expert.placed``) and
    handing it back there (continuous mode, the operator's own hand-back; the policy's history restarts)."""
    seeds = list(range(seed, seed + episodes))
    alone, _ = run_assisted(policy, task, seeds, None, config=AssistConfig(n_envs=n_envs), progress=progress)
    cfg = AssistConfig(
        hand_back="continuous",
        return_after=None,
        operator_hands_back=True,
        operator_hands_back_at="placed",
        n_envs=n_envs,
    )
    eps, _ = run_assisted(policy, task, seeds, AtStep(policy, AtStepConfig(at=0)), config=cfg, progress=progress)
    rows = []
    for ep in eps:
        ran = [i for i, by_operator in enumerate(ep.operator) if by_operator]
        after = ran[-1] + 1 if ran else 0
        closed = any(float(a[9]) > 0 for a, op in zip(ep.actions[after:], ep.operator[after:], strict=True) if not op)
        rows.append(PregraspEpisode(ep.seed, len(ran), closed, ep.success, len(ep.actions) - after))
    return TaskPregrasp(task, policy_name, seeds, float(np.mean([e.success for e in alone])), rows)

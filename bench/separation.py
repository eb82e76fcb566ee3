"""``hitl report separation``: how well each assistance signal tells shifted states from training ones.

The policy rolls out autonomously through the one controller on its training task and on each
shifted task (seeded; the states are cached next to the policy, ``policy.signal_data``); every
signal in the registry scores every visited state, each episode replayed in order as the fleet
would score it, and the AUROC says how often a shifted state
scores above a training-distribution state (0.5: no better than chance; below 0.5: the signal is
*higher* on the training distribution). Signals that need auxiliary networks are scored only when
``hitl train-signal`` has trained them next to the policy; the report says which were skipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.metrics import roc_auc_score

from policy.diffusion_policy import DiffusionPolicy
from policy.signal_data import policy_rollouts
from policy.signals.base import SignalError, StepSet
from policy.signals.registry import SIGNALS, load_signal, make_signal
from policy.signals.sampling import replay_series


@dataclass(frozen=True)
class SeparationReport:
    """auroc[signal][shift task]; states[task]: how many states were scored; skipped[signal]: why."""

    in_task: str
    seeds: list[int]
    states: dict[str, int]
    auroc: dict[str, dict[str, float]]
    skipped: dict[str, str]

    def to_dict(self) -> dict:
        return {
            "in_task": self.in_task,
            "seeds": self.seeds,
            "states": self.states,
            "auroc": self.auroc,
            "skipped": self.skipped,
        }

    def markdown(self) -> str:
        shift = [t for t in self.states if t != self.in_task]
        lines = [
            f"| signal | {' | '.join(f'`{t}`' for t in shift)} |",
            f"|---|{'---|' * len(shift)}",
        ]
        for name, row in self.auroc.items():
            lines.append(f"| {name} | {' | '.join(f'{row[t]:.2f}' for t in shift)} |")
        if self.skipped:
            lines += ["", "Not scored:"] + [f"- {name}: {why}" for name, why in self.skipped.items()]
        return "\n".join(lines)


def _signal(policy: DiffusionPolicy, policy_dir: Path, name: str):
    """The trained and calibrated signal when there is one, else the default (scores need no threshold);
    None and the reason where the signal cannot score without training."""
    try:
        return load_signal(policy, policy_dir, name), None
    except SignalError as exc:
        if SIGNALS[name].has_models:
            return None, f"not trained next to this policy ({exc})"
    try:
        return make_signal(name, policy), None
    except (SignalError, ValueError) as exc:
        return None, str(exc)


def auroc(in_scores: np.ndarray, shift_scores: np.ndarray) -> float:
    """P(a shifted state scores above a training state), ties counted half."""
    labels = np.r_[np.zeros(len(in_scores)), np.ones(len(shift_scores))]
    return float(roc_auc_score(labels, np.r_[in_scores, shift_scores]))


def shift_separation(
    policy: DiffusionPolicy,
    policy_dir: str | Path,
    in_task: str,
    shift_tasks: list[str],
    episodes: int = 8,
    seed: int = 1000,
    signals: list[str] | None = None,
    progress: bool = True,
) -> SeparationReport:
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    unknown = sorted(set(signals or []) - set(SIGNALS))
    if unknown:
        raise ValueError(f"unknown signals {unknown}; registered: {', '.join(SIGNALS)}")
    policy_dir = Path(policy_dir)
    seeds = list(range(seed, seed + episodes))
    steps: dict[str, StepSet] = {
        task: policy_rollouts(policy, policy_dir, task, seeds, progress=progress) for task in [in_task, *shift_tasks]
    }
    table: dict[str, dict[str, float]] = {}
    skipped: dict[str, str] = {}
    for name in signals or list(SIGNALS):
        signal, why = _signal(policy, policy_dir, name)
        if signal is None:
            skipped[name] = why
            continue
        scores = {  # each episode replayed in order: stateful signals (stac's running sum) see their history
            task: np.concatenate(replay_series(signal, s, s.episodes(), progress, f"{name} on {task}"))
            for task, s in steps.items()
        }
        table[name] = {task: auroc(scores[in_task], scores[task]) for task in shift_tasks}
    return SeparationReport(in_task, [seeds[0], seeds[-1]], {t: len(s) for t, s in steps.items()}, table, skipped)

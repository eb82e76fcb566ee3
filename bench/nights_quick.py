"""``hitl bench nights --quick``: the whole loop on a tiny fleet, for CI, in a few minutes.

The fleet's policy is made the way a user makes one, with the project's own commands (``hitl demos``,
``hitl train``, ``hitl calibrate``, ``hitl train-signal``), only small: a few lift-cube
demonstrations (with the recipe that records them again), a small MLP trained briefly, its
threshold and the fleet's default signal. One robot works lift-cube, one lift-hammer; the robots ask
at every step (the signal's threshold is set below any score), so every episode is a takeover, and
the night's job trains a few hundred steps and evaluates on two held-out seeds per task. What it
measures is the loop's plumbing (the scheduler fires, the job trains on what the service recorded,
the gate decides, the next day runs on what the registry serves), not the policy's learning.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

QUICK_DEMOS = 4
QUICK_TRAIN_STEPS = 300


def _hitl(*args: str) -> None:
    cmd = [sys.executable, "-m", "hitl.cli", *args]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} failed ({done.returncode}): {done.stderr[-2000:]}")


def quick_policy(root: Path) -> Path:
    """A small lift policy under ``root`` (its demonstrations in ``root/demos``), with its threshold
    and the fleet's default signal, asking at every step."""
    demos, policy = root / "demos", root / "policy"
    _hitl("demos", "--task", "lift-cube", "--episodes", str(QUICK_DEMOS), "--out", str(demos), "--quiet")
    _hitl(
        "train", "--task", "lift-cube", "--data", str(demos), "--out", str(policy), "--network", "mlp",
        "--obs-encoder-dims", "--steps", str(QUICK_TRAIN_STEPS), "--batch-size", "64", "--ddim-steps", "2",
        "--threads", "1", "--quiet",
    )  # fmt: skip
    _hitl("calibrate", "--policy", str(policy), "--data", str(demos), "--rollouts", "0", "--quiet")
    _hitl("train-signal", "--policy", str(policy), "--signal", "choice-stall", "--data", str(demos), "--quiet")
    signal = policy / "signals" / "choice-stall" / "config.json"
    doc = json.loads(signal.read_text())
    doc["calibration"]["threshold"] = -1.0  # every score is over it: each robot asks at once
    signal.write_text(json.dumps(doc, indent=2))
    return policy


def quick_config(root: Path, policy: Path, **finetune) -> Path:
    """The tiny fleet's settings file: two robots on ``policy``, budgeted takeovers of 4 steps, a nightly
    job that trains briefly and evaluates on 2 seeds per task (``finetune`` overrides its settings)."""
    ft = {
        "schedule": "0 3 * * *",
        "steps": 200,
        "eval_episodes": 2,
        "fit_episodes": 2,
        "threads": 1,
        "lease_seconds": 5.0,
        "idle_priority": False,
        "eval_tasks": {policy.name: ["lift-hammer"]},
        **finetune,
    }
    lines = [
        "control_hz = 20",
        "[workers]",
        'kind = "in-process"',
        "[inference]",
        "trace_policies = false",
        "[controller]",
        'hand_back = "budgeted"',
        "budget = 4",
        "cooldown = 0",
        "",
        "[finetune]",
        *(f"{k} = {json.dumps(v)}" for k, v in ft.items() if not isinstance(v, dict)),
    ]
    for key, table in ((k, v) for k, v in ft.items() if isinstance(v, dict)):
        lines += ["", f"[finetune.{key}]", *(f"{json.dumps(k)} = {json.dumps(v)}" for k, v in table.items())]
    for task in ("lift-cube", "lift-hammer"):
        lines += ["", "[[robots]]", f'task = "{task}"', "count = 1", f"policy = {json.dumps(str(policy))}"]
    out = root / "quick.toml"
    out.write_text("\n".join(lines) + "\n")
    return out

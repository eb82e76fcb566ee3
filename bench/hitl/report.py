"""Summaries of ``hitl bench hitl`` runs: sweep curves, the fewest assisted steps that reach a success
rate, false alarms, per-state diagnostics; the markdown of ``docs/benchmarks/hitl.md`` and its figures.

Per-state ground truth ("this state needs help"), two labels, AUROC per signal and task; negatives
are every step of an episode the same policy completed on its own (on any task it was run on):

- *late* (``NEEDS_HELP_WINDOW``): the last steps before the end of an episode the policy failed on its
  own. It rewards detecting a failure once it happens, when help often no longer rescues anything.
- *floor* (given the floor's summary, ``hitl bench floor``): in an episode the policy fails on its own
  and the floor's oracle brings through on the same seed, the ``budget`` states from the oracle's first
  request on, which the autonomous run passes too (up to that request the two episodes are the same):
  the states where help rescues the episode.
"""

from __future__ import annotations

import math

import numpy as np

from bench.hitl.run import FULL_TELEOP, RANDOM, REFERENCE
from bench.separation import auroc

NEEDS_HELP_WINDOW = 10  # steps before an autonomous failure's end that count as needing help
TARGETS = (1.0, 0.95)

# The paper's simulated table: human-assisted steps per episode for 100% success.
PAPER = {
    "denoising": {"lift": 16.9, "cup-stack": 5.4, "open-drawer": 8.0},
    "diff-dagger": {"lift": 30.2, "cup-stack": 32.0, "open-drawer": 16.0},
    "thrifty": {"lift": 33.5, "cup-stack": 21.2, "open-drawer": 17.2},
    "hula-offline": {"lift": 55.7, "cup-stack": 54.0, "open-drawer": 21.7},
    "full-teleop": {"lift": 76.6, "cup-stack": 147.8, "open-drawer": 114.8},
}


def _point(entry: dict) -> dict | None:
    res = entry["result"]
    if res is None or "episodes" not in res:
        return None
    eps = res["episodes"]
    return {
        "label": entry["label"],
        "threshold": res.get("threshold"),
        "success_rate": float(np.mean([e["success"] for e in eps])),
        "assisted_steps": float(np.mean([e["assisted_steps"] for e in eps])),
        "events": float(np.mean([e["events"] for e in eps])),
        "steps": float(np.mean([e["steps"] for e in eps])),
        "help_rate": res.get("help_rate"),
        "seconds": res.get("seconds"),
    }


def fewest_steps(curve: list[dict], target: float) -> dict | None:
    """The point of ``curve`` with the fewest assisted steps among those reaching ``target`` success."""
    ok = [p for p in curve if p["success_rate"] >= target - 1e-9]
    return min(ok, key=lambda p: p["assisted_steps"]) if ok else None


def summarize(raw: dict, floor: dict | None = None) -> dict:
    """The run's summary; ``floor``: the floor's summary (``hitl bench floor``) for the *floor* label."""
    recipe = raw["recipe"]
    tasks: dict[str, dict] = {t: {"signals": {}} for t in recipe["tasks"]}
    for entry in raw["assisted"]:
        t, s = entry["task"], entry["signal"]
        row = tasks[t]["signals"].setdefault(s, {"default": None, "curve": [], "skipped": None, "pending": 0})
        row["pending"] += int(bool(entry.get("pending")))
        res = entry["result"]
        if res is not None and "skipped" in res and "episodes" not in res:
            row["skipped"] = res["skipped"]
            continue
        point = _point(entry)
        if point is None:
            continue
        if entry["label"] == REFERENCE:
            row["default"] = point
        else:
            row["curve"].append(point)
    for t, row in tasks.items():
        for r in row["signals"].values():
            r["curve"].sort(key=lambda p: p["assisted_steps"])
            points = r["curve"] + ([r["default"]] if r["default"] else [])
            for target in TARGETS:
                r[f"best_{int(round(target * 100))}"] = fewest_steps(points, target)
        shadow = raw["shadow"].get(t)
        if shadow:
            row["autonomous_success"] = float(np.mean([e["success"] for e in shadow["episodes"]]))
    return {
        "recipe": recipe,
        "recipe_hash": raw["recipe_hash"],
        "pending_cells": raw.get("pending_cells", 0),
        "tasks": tasks,
        "false_alarms": false_alarms(raw),
        "diagnostics": diagnostics(raw, floor=floor),
        "skipped": {p: r["skipped"] for p, r in raw["reference"].items() if r.get("skipped")},
    }


def false_alarms(raw: dict) -> dict:
    """Per signal, on ``false_alarm_task`` episodes that succeed on their own: the share of steps its
    own calibrated rule asks for help, the share of episodes in which it asks at all (the rule run over
    the episode in shadow: no takeover follows, so a robot that asked is scored on as if it had not),
    and the share of steps above each swept threshold."""
    task = raw["recipe"].get("false_alarm_task")
    shadow = raw["shadow"].get(task) if task else None
    if not shadow:
        return {}
    ok = [e for e in shadow["episodes"] if e["success"]]
    out = {"task": task, "episodes": len(ok), "signals": {}}
    policies = raw["recipe"]["policies"]
    thresholds: dict[str, dict[str, float]] = {}  # the swept thresholds of the same policy's signals
    for entry in raw["assisted"]:
        res = entry["result"]
        same = policies[entry["task"]] == policies[task]
        if same and res and "threshold" in res and entry["label"] != REFERENCE:
            thresholds.setdefault(entry["signal"], {})[entry["label"]] = res["threshold"]
    labels = sorted({k for e in ok for k in e["scores"]})
    for s in labels:
        scores = np.asarray([v for e in ok for v in e["scores"][s]], dtype=np.float64)
        wants = [v for e in ok for v in e.get("wants", {}).get(s, [])]
        asked = [any(e["wants"][s]) for e in ok if e.get("wants", {}).get(s)]
        row = {
            "default": float(np.mean(wants)) if wants else None,
            "episodes_asking": float(np.mean(asked)) if asked else None,  # episodes its rule asks in at all
            "by_threshold": {},
        }
        for label, thr in sorted(thresholds.get(s, {}).items()):
            if s != RANDOM:
                row["by_threshold"][label] = float(np.mean(scores > thr)) if len(scores) else None
        out["signals"][s] = row
    return out


def _needs_help(episodes: list[dict], window: int) -> tuple[dict[str, list], dict[str, list]]:
    """(positives, negatives) per signal from shadow episodes."""
    pos: dict[str, list] = {}
    neg: dict[str, list] = {}
    for e in episodes:
        for s, vals in e["scores"].items():
            vals = [v for v in vals if math.isfinite(v)]
            if e["success"]:
                neg.setdefault(s, []).extend(vals)
            else:
                pos.setdefault(s, []).extend(vals[-window:])
    return pos, neg


def floor_labels(floor: dict, task: str, shadow: list[dict], budget: int) -> dict[int, list[int]]:
    """The *floor* label's positive steps, per shadow episode index: where the episode fails alone and
    the floor's chosen oracle (its floor, else its best finalist) brought the same seed through, the
    ``budget`` steps from the oracle's first request on. Empty where the floor has no episodes for the
    task (a summary written before they were recorded)."""
    row = (floor.get("tasks") or {}).get(task)
    chosen = row and (row.get("floor") or row.get("best"))
    if not chosen or "episodes" not in chosen:
        return {}
    rescued = {
        e["seed"]: e["first_request"] for e in chosen["episodes"] if e["success"] and e["first_request"] is not None
    }
    out = {}
    for i, e in enumerate(shadow):
        k = rescued.get(e.get("seed"))
        if not e["success"] and k is not None and k < e["steps"]:
            out[i] = list(range(k, min(k + budget, e["steps"])))
    return out


def diagnostics(raw: dict, window: int = NEEDS_HELP_WINDOW, floor: dict | None = None) -> dict:
    """AUROC of every signal for "this state needs help", per task (negatives: every successful
    autonomous episode of the same policy, on any task it ran), by the *late* label and, given the
    floor's summary, by the *floor* label (see the module)."""
    policies = raw["recipe"]["policies"]
    negatives: dict[str, dict[str, list]] = {}
    for t, shadow in raw["shadow"].items():
        _, neg = _needs_help(shadow["episodes"], window)
        for s, v in neg.items():
            negatives.setdefault(policies[t], {}).setdefault(s, []).extend(v)
    out = {"window": window, "tasks": {}}
    for t, shadow in raw["shadow"].items():
        pos, _ = _needs_help(shadow["episodes"], window)
        neg = negatives.get(policies[t], {})
        row = {"positives": len(next(iter(pos.values()), [])), "negatives": len(next(iter(neg.values()), []))}
        row["auroc"] = {
            s: auroc(np.asarray(neg[s]), np.asarray(pos[s])) if pos.get(s) and neg.get(s) else None
            for s in sorted(set(pos) | set(neg))
            if s not in (FULL_TELEOP,)
        }
        if floor is not None:
            labels = floor_labels(floor, t, shadow["episodes"], raw["recipe"]["budget"])
            fpos: dict[str, list] = {}
            for i, steps in labels.items():
                for s, vals in shadow["episodes"][i]["scores"].items():
                    fpos.setdefault(s, []).extend(v for k in steps if k < len(vals) and math.isfinite(v := vals[k]))
            row["floor_positives"] = len(next(iter(fpos.values()), []))
            row["floor_episodes"] = len(labels)
            row["auroc_floor"] = {
                s: auroc(np.asarray(neg[s]), np.asarray(fpos[s])) if fpos.get(s) and neg.get(s) else None
                for s in sorted(set(pos) | set(neg))
                if s not in (FULL_TELEOP,)
            }
        row["peak_step"] = peak_steps(shadow["episodes"])
        out["tasks"][t] = row
    return out


def peak_steps(episodes: list[dict]) -> dict[str, dict]:
    """Per signal, where in the episode its score peaks: the median step of each episode's maximum,
    and the same as a share of the episode's length."""
    out: dict[str, dict] = {}
    names = sorted({s for e in episodes for s in e["scores"]} - {FULL_TELEOP, RANDOM})
    for s in names:
        steps, shares = [], []
        for e in episodes:
            v = np.asarray(e["scores"].get(s, []), dtype=np.float64)
            if len(v) and np.isfinite(v).any():
                i = int(np.nanargmax(v))
                steps.append(i)
                shares.append(i / max(len(v) - 1, 1))
        out[s] = {"median_step": float(np.median(steps)), "median_share": float(np.median(shares))} if steps else {}
    return out

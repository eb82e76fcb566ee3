"""``hitl bench hitl``: how many human steps each assistance signal costs to bring episodes to success.

The paper's protocol (``docs/benchmarks/hitl.md``): every episode runs through the fleet's ``Controller``
(``lab.assisted.run_assisted``), batched across all of a task's episodes; the asking signal
decides when the robot asks; the simulated operator (the task's scripted expert, driving from the
operator view only) answers with ``budget`` steps of delta-pose and gripper commands per request.

What one run measures, per task and signal:

- a threshold sweep: thresholds at the ``quantiles`` of the signal's own scores on the policy's
  training task (reference rollouts, seeds apart from the evaluation's), so every signal is swept
  over the same in-distribution ask rates; ``random`` is swept over the matching rates 1 - q;
- the result at the signal's own calibration (``hitl calibrate`` / ``hitl train-signal``);
- ``full-teleop``: the operator drives every step;
- shadow runs of the policy alone with every signal scored: false alarms (the share of steps that
  would ask, on ``false_alarm_task`` episodes that succeed on their own) and the per-state
  diagnostics (``bench.hitl.report``).

Every unit of work is a ``Cell`` whose result is cached under ``cache_dir`` by the hash of what
determines it (weights, signal files, settings, seeds, code version), so reruns are incremental.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from policy.checkpoint import CALIBRATION, WEIGHTS
from storage.paths import resolve

VERSION = 2  # bump when a change alters what a cell computes
DEFAULT_QUANTILES = (0.25, 0.5, 0.75, 0.9, 0.95, 0.98)
QUICK_QUANTILES = (0.5, 0.9, 0.98)
REFERENCE = "reference"  # the threshold label of the signal's own calibration
FULL_TELEOP = "full-teleop"
RANDOM = "random"


class BenchError(ValueError):
    """The benchmark cannot run as asked; the message says why."""


@dataclass(frozen=True)
class SignalSpec:
    """A registered signal, optionally with config overrides (ablations): ``denoising:radius=0.01``."""

    name: str
    settings: tuple[tuple[str, object], ...] = ()

    @property
    def label(self) -> str:
        if not self.settings:
            return self.name
        return self.name + "[" + ",".join(f"{k}={v}" for k, v in self.settings) + "]"

    @classmethod
    def parse(cls, text: str) -> SignalSpec:
        name, _, rest = text.partition(":")
        settings = []
        for pair in filter(None, rest.split(",")):
            if "=" not in pair:
                raise BenchError(f"signal spec {text!r}: expected name:key=value,key=value")
            k, v = pair.split("=", 1)
            try:
                value = json.loads(v)
            except json.JSONDecodeError:
                value = v
            settings.append((k.strip(), value))
        return cls(name.strip(), tuple(settings))


@dataclass(frozen=True)
class Recipe:
    """What a benchmark run measures. policies: task -> policy folder (each task's policy; its
    training task is the one its config names, where the reference rollouts run)."""

    policies: tuple[tuple[str, str], ...]
    tasks: tuple[str, ...]
    signals: tuple[SignalSpec, ...]
    quantiles: tuple[float, ...] = DEFAULT_QUANTILES
    false_alarm_task: str | None = "lift-cube"
    episodes: int = 20
    seed: int = 1000
    reference_episodes: int = 10
    reference_seed: int = 5000
    budget: int = 4
    envs: int = 20
    sweep: bool = True  # False: only each signal's own calibration and full teleoperation
    shadow: bool = True  # shadow runs for false alarms and diagnostics
    exhaustive: bool = False  # sweep every threshold, not only down to the first with 100% success

    def __post_init__(self) -> None:
        for name in ("episodes", "reference_episodes", "budget", "envs"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise BenchError(f"{name} must be an integer >= 1, got {v!r}")
        for q in self.quantiles:
            if not (isinstance(q, int | float) and 0 < q < 1):
                raise BenchError(f"quantiles must be in (0, 1), got {q!r}")
        missing = [t for t in self.all_tasks if t not in dict(self.policies)]
        if missing:
            raise BenchError(f"no policy given for task(s) {missing}")

    @property
    def all_tasks(self) -> tuple[str, ...]:
        extra = (self.false_alarm_task,) if self.false_alarm_task and self.false_alarm_task not in self.tasks else ()
        return tuple(self.tasks) + extra

    def policy_for(self, task: str) -> str:
        return dict(self.policies)[task]

    @property
    def seeds(self) -> list[int]:
        return list(range(self.seed, self.seed + self.episodes))

    @property
    def reference_seeds(self) -> list[int]:
        return list(range(self.reference_seed, self.reference_seed + self.reference_episodes))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["policies"] = dict(self.policies)
        d["signals"] = [s.label for s in self.signals]
        return d

    def digest(self) -> str:
        return _hash(self.to_dict())


# -- cells ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    """One unit of work. kind: ``shadow`` (the policy alone, every signal scored) or ``assist`` (the
    signal ``spec`` asks, at ``threshold``; None: its own calibration)."""

    kind: str
    task: str
    policy: str
    seeds: tuple[int, ...]
    budget: int
    envs: int
    spec: SignalSpec | None = None
    specs: tuple[SignalSpec, ...] = ()
    threshold: float | None = None
    label: str = REFERENCE  # the threshold's name: a quantile, "reference" or a random rate
    key: str = field(default="", compare=False)

    def keyed(self) -> Cell:
        files = {"policy": _files_digest(Path(self.policy))}
        for s in ([self.spec] if self.spec else []) + list(self.specs):
            files[s.label] = _files_digest(Path(self.policy) / "signals" / s.name)
        doc = {"version": VERSION, "cell": _cell_doc(self), "files": files}
        return Cell(**{**self.__dict__, "key": _hash(doc)})


def _cell_doc(cell: Cell) -> dict:
    d = {k: v for k, v in cell.__dict__.items() if k != "key"}
    d["spec"] = cell.spec.label if cell.spec else None
    d["specs"] = [s.label for s in cell.specs]
    d["seeds"] = list(cell.seeds)
    return d


def _hash(doc: dict) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _files_digest(folder: Path) -> str:
    h = hashlib.sha256()
    for name in ("config.json", WEIGHTS, CALIBRATION):
        path = folder / name
        if path.is_file():
            h.update(name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def load_spec(policy, policy_dir: str | Path, spec: SignalSpec):
    """The signal as saved next to the policy, with ``spec``'s overrides applied. A variant is
    calibrated afresh on the policy's validation demonstrations when the folder it was trained from is
    still there (its own calibration); otherwise it has none (the sweep sets its thresholds)."""
    from policy.checkpoint import read_info
    from policy.signal_data import demo_data
    from policy.signals import load_signal, make_signal

    signal = load_signal(policy, policy_dir, spec.name)
    if not spec.settings:
        return signal
    if signal.has_models or signal.needs_rollouts:
        raise BenchError(f"{spec.label}: overrides are for signals that calibrate on demonstrations alone")
    variant = make_signal(spec.name, policy, {**signal.config.to_dict(), **dict(spec.settings)})
    variant.calibration = None
    info = read_info(policy_dir)
    recorded = (info.get("dataset") or {}).get("folder")
    folder = resolve(recorded) if recorded else None
    if folder and folder.is_dir():
        variant.calibrate(demo_data(policy, info, folder))
    return variant


def _with_threshold(signal, threshold: float, label: str) -> None:
    if signal.name == RANDOM:
        signal.match_rate(1.0 - threshold if label.startswith("q") else threshold, label)
        return
    signal.calibration = {**(signal.calibration or {}), "threshold": float(threshold), "source": label}


def run_cell(cell: Cell, threads: int | None = 1) -> dict:
    """Runs one cell (in a worker process or here) and returns its JSON-able result."""
    import torch

    from lab.assisted import AssistConfig, run_assisted
    from policy.checkpoint import check_fits, load_policy
    from policy.signals import SignalError

    if threads:
        torch.set_num_threads(threads)
    policy, info = load_policy(cell.policy)
    check_fits(info, cell.task, cell.policy)
    cfg = AssistConfig(hand_back="budgeted", budget=cell.budget, n_envs=cell.envs)
    seeds = list(cell.seeds)
    if cell.kind == "shadow":
        signals, skipped = {}, {}
        for spec in cell.specs:
            try:
                signals[spec.label] = load_spec(policy, cell.policy, spec)
            except (SignalError, BenchError) as exc:
                skipped[spec.label] = str(exc)
        episodes, timing = run_assisted(policy, cell.task, seeds, None, signals, cfg, progress=False)
        return {
            "cell": _cell_doc(cell),
            "skipped": skipped,
            "seconds": timing["seconds"],
            "episodes": [
                {
                    "seed": e.seed,
                    "success": e.success,
                    "steps": e.steps,
                    "scores": {k: [round(float(v), 7) for v in vals] for k, vals in e.scores.items()},
                    "wants": {k: [int(v) for v in vals] for k, vals in e.wants.items() if signals[k].calibration},
                }
                for e in episodes
            ],
        }
    assert cell.spec is not None
    try:
        signal = load_spec(policy, cell.policy, cell.spec)
        if cell.threshold is not None:
            _with_threshold(signal, cell.threshold, cell.label)
        threshold = float(signal.threshold)  # SignalError when the signal has no calibration to run at
    except (SignalError, BenchError) as exc:
        return {"cell": _cell_doc(cell), "skipped": str(exc)}
    episodes, timing = run_assisted(policy, cell.task, seeds, signal, None, cfg, progress=False)
    return {
        "cell": _cell_doc(cell),
        "threshold": threshold,
        "seconds": timing["seconds"],
        "episodes": [e.summary() for e in episodes],
        "help_rate": _help_rate(episodes),
    }


def _help_rate(episodes) -> float | None:
    asked = sum(e.events for e in episodes)
    auto = sum(int(np.sum(e.policy_in_control)) for e in episodes)
    return asked / auto if auto else None


class Cache:
    """Cell results as JSON files named by the cell's key."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def path(self, cell: Cell) -> Path:
        return self.folder / f"{cell.kind}-{cell.task}-{cell.key}.json"

    def get(self, cell: Cell) -> dict | None:
        path = self.path(cell)
        if not path.is_file():
            return None
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError:
            path.unlink(missing_ok=True)  # a damaged entry runs again
            return None

    def put(self, cell: Cell, result: dict) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.path(cell).with_suffix(".tmp")
        tmp.write_text(json.dumps(result))
        tmp.replace(self.path(cell))


def run_cells(
    cells: list[Cell], cache: Cache, jobs: int = 1, progress: bool = True, desc: str = "cells"
) -> dict[str, dict]:
    """Results of ``cells`` by key: cached ones read back, the others run (``jobs`` processes)."""
    return run_chains([[c] for c in cells], cache, jobs, progress, desc)


def run_chains(
    chains: list[list[Cell]],
    cache: Cache,
    jobs: int = 1,
    progress: bool = True,
    desc: str = "cells",
    stop: Callable[[dict], bool] | None = None,
    work: Callable[[Cell], dict] = run_cell,
) -> dict[str, dict]:
    """Runs each chain's cells in order, dropping the rest of a chain once ``stop(result)`` holds (a
    sweep that reached 100% success); chains run side by side on ``jobs`` processes. Cached results
    are read back, not run. ``work`` computes one cell (a module-level function, for the processes)."""
    out: dict[str, dict] = {}
    queues = [list(c) for c in chains]
    bar = tqdm(total=sum(len(q) for q in queues), desc=desc, disable=not progress, unit="cell")

    def finish(i: int, cell: Cell, result: dict) -> None:
        out[cell.key] = result
        queues[i].pop(0)
        bar.update(1)
        if stop is not None and stop(result) and queues[i]:
            bar.total -= len(queues[i])
            queues[i].clear()
            bar.refresh()

    def next_to_run(i: int) -> Cell | None:
        while queues[i]:
            cell = queues[i][0]
            hit = out.get(cell.key) or cache.get(cell)
            if hit is None:
                return cell
            finish(i, cell, hit)
        return None

    try:
        if jobs <= 1:
            for i in range(len(queues)):
                while (cell := next_to_run(i)) is not None:
                    finish(i, cell, _store(cache, cell, work(cell)))
        else:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                futures = {}
                for i in range(len(queues)):
                    if (cell := next_to_run(i)) is not None:
                        futures[pool.submit(work, cell)] = (i, cell)
                while futures:
                    done = next(as_completed(futures))
                    i, cell = futures.pop(done)
                    finish(i, cell, _store(cache, cell, done.result()))
                    if (cell := next_to_run(i)) is not None:
                        futures[pool.submit(work, cell)] = (i, cell)
    finally:
        bar.close()
    return out


def _store(cache: Cache, cell: Cell, result: dict) -> dict:
    cache.put(cell, result)
    return result


# -- the run -------------------------------------------------------------------------------------------
def policy_task(policy_dir: str) -> str:
    config = json.loads((Path(policy_dir) / "config.json").read_text())
    task = config.get("task")
    if not task:
        raise BenchError(f"{policy_dir}/config.json names no task: cannot pick its reference task")
    return task


def thresholds_from(scores: list[float], quantiles: tuple[float, ...]) -> dict[str, float]:
    values = np.asarray([v for v in scores if np.isfinite(v)], dtype=np.float64)
    if len(values) == 0:
        return {}
    return {quantile_label(q): float(np.quantile(values, q)) for q in quantiles}


def quantile_label(q: float) -> str:
    return f"q{q:g}"


def shadow_scores(result: dict, label: str, success: bool | None = None) -> list[float]:
    out: list[float] = []
    for e in result["episodes"]:
        if success is None or e["success"] == success:
            out += e["scores"].get(label, [])
    return out


def run_benchmark(
    recipe: Recipe,
    cache_dir: str | Path,
    jobs: int = 1,
    progress: bool = True,
    cached_only: bool = False,
) -> dict:
    """Runs (or reads from the cache) every cell of ``recipe``; returns the raw results for
    ``bench.hitl.report.summarize`` (cells a sweep did not need have no result). ``cached_only``
    runs nothing: cells not in the cache yet are marked ``pending`` (a report of a run in progress)."""
    cache = Cache(cache_dir)

    def runner(cells: list[Cell], desc: str) -> dict[str, dict]:
        if cached_only:
            return {c.key: hit for c in cells if (hit := cache.get(c)) is not None}
        return run_cells(cells, cache, jobs, progress, desc)

    def runner_chains(chains: list[list[Cell]], desc: str, stop) -> dict[str, dict]:
        if cached_only:
            return runner([c for chain in chains for c in chain], desc)
        return run_chains(chains, cache, jobs, progress, desc, stop)

    specs = tuple(s for s in recipe.signals if s.name not in (FULL_TELEOP,))

    def cell(**kw) -> Cell:
        return Cell(budget=recipe.budget, envs=recipe.envs, **kw).keyed()

    # 1. shadow runs: reference rollouts on each policy's own task, and every task's evaluation seeds
    policies = sorted({recipe.policy_for(t) for t in recipe.all_tasks})
    reference = {
        p: cell(kind="shadow", task=policy_task(p), policy=p, seeds=tuple(recipe.reference_seeds), specs=specs)
        for p in policies
    }
    shadows = {}
    if recipe.shadow:
        shadows = {
            t: cell(kind="shadow", task=t, policy=recipe.policy_for(t), seeds=tuple(recipe.seeds), specs=specs)
            for t in recipe.all_tasks
        }
    first = list(reference.values()) + list(shadows.values())
    done = runner(first, "shadow runs")
    missing = [p for p, c in reference.items() if c.key not in done]
    if missing:  # only with cached_only: the thresholds of these policies' sweeps are not known yet
        return {"recipe": recipe.to_dict(), "recipe_hash": recipe.digest(), "pending_references": missing}
    # 2. assisted runs: each signal at its own calibration, and its sweep from the fewest asks down
    #    (stopping at the first threshold that brings every episode to success, unless exhaustive)
    assisted: list[tuple[str, str, str, Cell]] = []
    chains: list[list[Cell]] = []
    for t in recipe.tasks:
        p = recipe.policy_for(t)
        ref = done[reference[p].key]
        for spec in recipe.signals:
            base = dict(kind="assist", task=t, policy=p, seeds=tuple(recipe.seeds), spec=spec)
            c = cell(**base)  # its own calibration (a variant's made afresh, when the demonstrations are here)
            assisted.append((t, spec.label, REFERENCE, c))
            chains.append([c])
            if spec.name == FULL_TELEOP or not recipe.sweep:
                continue
            if spec.name == RANDOM:
                grid = {quantile_label(q): q for q in recipe.quantiles}  # rate 1 - q
            elif spec.label in ref["skipped"]:
                continue
            else:
                grid = thresholds_from(shadow_scores(ref, spec.label), recipe.quantiles)
            chain = []
            for label in sorted(grid, key=lambda lab: -float(lab[1:])):
                c = cell(**base, threshold=grid[label], label=label)
                assisted.append((t, spec.label, label, c))
                chain.append(c)
            chains.append(chain)
    stop = None if recipe.exhaustive else _all_succeeded
    results = runner_chains(chains, "assisted runs", stop)
    pending = set()
    for chain in chains:  # cells still to run: no result, and no earlier cell of the chain ended it
        for c in chain:
            if c.key in results:
                if stop is not None and stop(results[c.key]):
                    break
            else:
                pending.add(c.key)
    return {
        "recipe": recipe.to_dict(),
        "recipe_hash": recipe.digest(),
        "reference": {p: done[c.key] for p, c in reference.items()},
        "shadow": {t: done[c.key] for t, c in shadows.items() if c.key in done},
        "assisted": [
            {"task": t, "signal": s, "label": label, "result": results.get(c.key), "pending": c.key in pending}
            for t, s, label, c in assisted
        ],
        "pending_cells": len(pending),
    }


def _all_succeeded(result: dict) -> bool:
    eps = result.get("episodes") or []
    return bool(eps) and all(e["success"] for e in eps)


def default_jobs() -> int:
    return max(1, min(2, os.cpu_count() or 1))

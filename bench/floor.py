"""``hitl bench floor``: the fewest operator steps any asking signal could need on a policy and task.

The oracle (``bench.oracle``) asks from the simulator's privileged state, under the paper's protocol:
``budget`` operator steps per request (4), the simulated operator (``lab.assisted.ExpertOperator``, in
the style the recipe names), every episode through the one ``Controller``. Per task:

1. a sweep, on development seeds, of where the oracle asks (its windows and their reach) and for how
   long (the most requests per episode): every grid point on ``dev_episodes`` seeds;
2. the ``finalists`` grid points that brought every development episode to success with the fewest
   operator steps run on the evaluation seeds, with full teleoperation on the same seeds;
3. the floor: the finalist with the fewest assisted steps per episode at 100% success on the
   evaluation seeds, with its requests per episode and its ratio to full teleoperation. It is a
   best-of-sweep figure: the lowest cost found on this grid, an upper bound on the true floor.

A gap between a real signal and the floor is the signal's; the floor itself is the policy's and the
task's: a policy that undoes a correction, or a task a short correction cannot fix, keeps it high.
Cells are cached like ``hitl bench hitl``'s (``bench.hitl.run.Cache``), so reruns are incremental.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from bench.hitl.run import BenchError, Cache, Cell, SignalSpec, run_chains
from bench.oracle import OracleConfig, task_windows
from policy.hand_back import RESUME
from sim.experts import OperatorStyle

VERSION = 1  # bump when a change alters what a cell computes
FULL_TELEOP = "full-teleop"
# where the oracle asks (window, reach) and for how long (requests per episode: None, no cap)
GRID: dict[str, tuple[tuple[float, ...], tuple[int | None, ...]]] = {
    "grasp": ((0.05, 0.10, 0.20), (2, 4, 8, None)),
    "insertion": ((0.05, 0.10, 0.15), (4, 16, None)),
    "early": ((1, 2, 4, 6), (None,)),
    "astray": ((0.0, 0.05), (2, 8, None)),
}
# the paper's ratio to full teleoperation with its signal (Table I), per problem
PAPER = {"grasp": 0.22, "insertion": 0.04, "early": 0.07, "astray": 0.07}


@dataclass(frozen=True)
class FloorRecipe:
    """policies: task -> policy folder; operator: the simulated operator's ``OperatorStyle``."""

    policies: tuple[tuple[str, str], ...]
    tasks: tuple[str, ...]
    episodes: int = 20
    seed: int = 1000
    dev_episodes: int = 12
    dev_seed: int = 2000
    budget: int = 4
    finalists: int = 3
    operator: str = OperatorStyle.CARRY_ON
    resume: str = "restart"  # what the policy sees after a hand-back (``policy.hand_back.RESUME``)
    quick: bool = False  # one grid point per window: its widest reach, no cap (a smoke run)

    def __post_init__(self) -> None:
        for name in ("episodes", "dev_episodes", "budget", "finalists"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise BenchError(f"{name} must be an integer >= 1, got {v!r}")
        if self.resume not in RESUME:
            raise BenchError(f"resume must be one of {RESUME}, got {self.resume!r}")
        if self.operator not in tuple(OperatorStyle):
            raise BenchError(f"operator must be one of {[str(s) for s in OperatorStyle]}, got {self.operator!r}")
        missing = [t for t in self.tasks if t not in dict(self.policies)]
        if missing:
            raise BenchError(f"no policy given for task(s) {missing}")
        dev = set(range(self.dev_seed, self.dev_seed + self.dev_episodes))
        if dev & set(range(self.seed, self.seed + self.episodes)):
            raise BenchError("development and evaluation seeds overlap: the sweep would choose on the test")

    def to_dict(self) -> dict:
        return {**asdict(self), "policies": dict(self.policies)}


def grid(task: str, quick: bool = False) -> list[OracleConfig]:
    """The sweep's grid points for ``task``: each of its windows at each reach and request cap (``quick``:
    its widest reach with no cap only)."""
    out = []
    for window in task_windows(task):
        reaches, caps = GRID[window]
        if quick:
            reaches, caps = (max(reaches),), (None,)
        out += [OracleConfig(window=window, reach=r, requests=c) for r in reaches for c in caps]
    return out


def _spec(config: OracleConfig | None, recipe: FloorRecipe) -> SignalSpec:
    """The cell's driver and how its episodes run (a non-default ``resume`` only: the cells of the
    default keep their cache keys)."""
    run = (("operator", recipe.operator),) + ((("resume", recipe.resume),) if recipe.resume != "restart" else ())
    if config is None:
        return SignalSpec(FULL_TELEOP, run)
    return SignalSpec(
        "oracle", (("window", config.window), ("reach", config.reach), ("requests", config.requests), *run)
    )


def run_floor_cell(cell: Cell) -> dict:
    """One cell: the oracle (or full teleoperation) on the cell's seeds. Module-level for the processes."""
    import torch

    from bench.oracle import Oracle
    from lab.assisted import AssistConfig, run_assisted
    from policy.checkpoint import check_fits, load_policy
    from policy.signals import make_signal

    torch.set_num_threads(1)
    assert cell.spec is not None
    settings = dict(cell.spec.settings)
    operator = settings.pop("operator")
    resume = settings.pop("resume", "restart")
    policy, info = load_policy(cell.policy)
    check_fits(info, cell.task, cell.policy)
    on_reset = None
    if cell.spec.name == FULL_TELEOP:
        driver = make_signal(FULL_TELEOP, policy)
    else:
        driver = Oracle(policy, OracleConfig(**settings))
        on_reset = driver.watch
    cfg = AssistConfig(hand_back="budgeted", budget=cell.budget, n_envs=cell.envs, operator=operator, resume=resume)
    episodes, timing = run_assisted(policy, cell.task, list(cell.seeds), driver, None, cfg, False, on_reset)
    return {"seconds": timing["seconds"], "episodes": [e.summary() for e in episodes]}


REASK_WITHIN = 10  # policy steps after a hand-back in which a new request counts as a re-ask


def reasks(asked_at: list[int], budget: int) -> int:
    """Requests made within ``REASK_WITHIN`` policy steps of the previous request's hand-back: a request at
    step a holds once, the operator drives steps a+1 .. a+budget, the policy is back from a+budget+1."""
    return sum(b - a - budget <= REASK_WITHIN for a, b in zip(asked_at, asked_at[1:], strict=False))


def _outcome(result: dict, budget: int) -> dict:
    eps = result["episodes"]
    return {
        "success_rate": float(np.mean([e["success"] for e in eps])),
        "assisted_steps": float(np.mean([e["assisted_steps"] for e in eps])),
        "requests": float(np.mean([e["events"] for e in eps])),
        "reasks": float(np.mean([reasks(e["asked_at"], budget) for e in eps])),
        "steps": float(np.mean([e["steps"] for e in eps])),
    }


def first_requests(result: dict) -> list[dict]:
    """Per evaluation episode: its seed, whether the oracle's help brought it through, and the step of
    the oracle's first request (None: it never asked). Up to that step the episode is the policy's
    own, so a benchmark's autonomous run of the same seed passes the same states: where the episode
    fails alone and succeeds here, they are the states where help rescues it
    (``bench.hitl.report.floor_labels``)."""
    return [
        {"seed": e["seed"], "success": bool(e["success"]), "first_request": e["asked_at"][0] if e["asked_at"] else None}
        for e in result["episodes"]
    ]


def _run(cache: Cache, cells: list[Cell], jobs: int, progress: bool, what: str) -> dict[str, dict]:
    return run_chains([[c] for c in cells], cache, jobs, progress, f"floor: {what}", work=run_floor_cell)


def run_floor(recipe: FloorRecipe, cache_dir, jobs: int = 1, progress: bool = True) -> dict:
    """Runs (or reads from the cache) the sweep, the finalists and full teleoperation; returns the
    per-task results, the floor first (None where no finalist reached 100% on the evaluation seeds)."""
    cache = Cache(cache_dir)
    dev_seeds = tuple(range(recipe.dev_seed, recipe.dev_seed + recipe.dev_episodes))
    seeds = tuple(range(recipe.seed, recipe.seed + recipe.episodes))
    label = f"floor-v{VERSION}"

    def cell(task: str, seeds: tuple[int, ...], config: OracleConfig | None) -> Cell:
        spec = _spec(config, recipe)
        policy = dict(recipe.policies)[task]
        return Cell("floor", task, policy, seeds, recipe.budget, len(seeds), spec=spec, label=label).keyed()

    sweep = {t: [(c, cell(t, dev_seeds, c)) for c in grid(t, recipe.quick)] for t in recipe.tasks}
    teleop = {t: cell(t, seeds, None) for t in recipe.tasks}
    first = [c for cells in sweep.values() for _, c in cells] + list(teleop.values())
    done = _run(cache, first, jobs, progress, "sweep")
    chosen: dict[str, list[tuple[OracleConfig, dict, Cell]]] = {}
    for t, cells in sweep.items():
        rows = [(c, _outcome(done[k.key], recipe.budget), cell(t, seeds, c)) for c, k in cells]
        # the fewest operator steps among those that brought every episode through; failing that, the most successes
        rows.sort(key=lambda r: (-r[1]["success_rate"], r[1]["assisted_steps"]))
        chosen[t] = rows[: recipe.finalists]
    final = _run(cache, [c for rows in chosen.values() for _, _, c in rows], jobs, progress, "finalists")
    tasks = {}
    for t in recipe.tasks:
        full = _outcome(done[teleop[t].key], recipe.budget)
        evaluated = []
        for config, dev, c in chosen[t]:
            ev = _outcome(final[c.key], recipe.budget)
            ev["ratio"] = ev["assisted_steps"] / full["assisted_steps"] if full["assisted_steps"] else None
            entry = {"oracle": config.to_dict() | {"label": config.label}, "dev": dev, "eval": ev}
            evaluated.append(entry | {"episodes": first_requests(final[c.key])})
        complete = [e for e in evaluated if e["eval"]["success_rate"] == 1.0]
        floor = min(complete, key=lambda e: e["eval"]["assisted_steps"]) if complete else None
        best = floor or max(evaluated, key=lambda e: (e["eval"]["success_rate"], -e["eval"]["assisted_steps"]))
        tasks[t] = {
            "policy": dict(recipe.policies)[t],
            "floor": floor,
            "best": best,
            "full_teleop": full,
            "paper_ratio": PAPER[best["oracle"]["window"]],
            "finalists": evaluated,
            "sweep": [
                {"oracle": c.to_dict() | {"label": c.label}, **_outcome(done[k.key], recipe.budget)}
                for c, k in sweep[t]
            ],
        }
    return {"recipe": recipe.to_dict(), "version": VERSION, "tasks": tasks}


def markdown(summary: dict, title: str = "") -> str:
    """The floor table: per task, the oracle's assisted steps, their ratio to full teleoperation and the
    requests per episode (best-of-sweep), beside the paper's ratio with its signal."""
    tasks = summary["tasks"]
    names = list(tasks)
    prov = summary.get("provenance", {})
    recipe = summary["recipe"]

    def cell(t: str, key: str, fmt: str) -> str:
        row = tasks[t]
        e = (row["floor"] or row["best"])["eval"]
        text = format(e[key], fmt) if e.get(key) is not None else "—"
        return text if row["floor"] else f"({text})"

    def row(name: str, values) -> str:
        return f"| {name} | " + " | ".join(values) + " |"

    chosen = {t: (tasks[t]["floor"] or tasks[t]["best"]) for t in names}
    lines = [title] if title else []
    lines += [
        f"Oracle, best-of-sweep: {recipe['dev_episodes']} development episodes per grid point (seeds "
        f"{recipe['dev_seed']}–{recipe['dev_seed'] + recipe['dev_episodes'] - 1}), the {recipe['finalists']} "
        f"cheapest at 100% run on the {recipe['episodes']} evaluation episodes (seeds {recipe['seed']}–"
        f"{recipe['seed'] + recipe['episodes'] - 1}); {recipe['budget']} operator steps per request; the "
        f"simulated operator in `{recipe['operator']}` style; after a hand-back the policy's history "
        + ("keeps the takeover's frames." if recipe.get("resume") == "history" else "restarts."),
        "",
        row("", names),
        "|---|" + "---|" * len(names),
        row("policy", (f"`{tasks[t]['policy']}`" for t in names)),
        row("**floor: assisted steps per episode**", (cell(t, "assisted_steps", ".1f") for t in names)),
        row("its ratio to full teleop", (cell(t, "ratio", ".2f") for t in names)),
        row("requests per episode", (cell(t, "requests", ".1f") for t in names)),
        row(f"of them within {REASK_WITHIN} steps of a hand-back", (cell(t, "reasks", ".1f") for t in names)),
        row("success", (cell(t, "success_rate", ".0%") for t in names)),
        row("where the oracle asks", (chosen[t]["oracle"]["label"] for t in names)),
        row("full teleop: steps per episode", (f"{tasks[t]['full_teleop']['assisted_steps']:.1f}" for t in names)),
        row("paper, its signal: ratio to full teleop", (f"{tasks[t]['paper_ratio']:.2f}" for t in names)),
        "",
        "Bracketed figures: no finalist reached 100% on the evaluation seeds; the best of them is shown.",
    ]
    if prov:
        lines += ["", f"`{prov.get('command', '')}`, {prov.get('machine', '')}, {prov.get('date', '')}."]
    return "\n".join(lines)

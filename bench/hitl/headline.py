"""The headline of ``docs/benchmarks/hitl.md``: the paper's table beside ours.

One row per source, one column per task, each cell the assisted steps per episode at 100% success as a
ratio to full teleoperation on the same seeds, with the requests per episode:

- the paper (its metric, and its best baseline: Table I, as ratios to its own full teleoperation);
- the floor (``hitl bench floor``: the oracle, best of its sweep);
- the fleet's asking signal at its shipped calibration: what the fleet runs;
- every other signal at the best threshold of its sweep, the paper's metric (``denoising``) first.

Where a row does not reach 100% on a task, the cell gives its best success and that point's ratio.
Written by ``hitl bench hitl --report ... --floor ... --default-signal ...`` into the ``headline``
section.
"""

from __future__ import annotations

from bench.hitl.report import PAPER
from bench.hitl.run import FULL_TELEOP

PAPER_COLUMN = {"lift-nut": "lift", "lift-hammer": "lift", "lift-hook": "lift"}
PAPER_METRIC = "denoising"
BASELINES = ("diff-dagger", "thrifty", "hula-offline")  # the paper's baselines (Table I)


def paper_ratio(signal: str, task: str) -> float | None:
    """The paper's assisted steps for ``signal`` over its full teleoperation's, on ``task``'s problem."""
    col = PAPER_COLUMN.get(task, task)
    if signal not in PAPER or col not in PAPER[signal]:
        return None
    return PAPER[signal][col] / PAPER[FULL_TELEOP][col]


def paper_best_baseline(task: str) -> tuple[str, float] | None:
    ratios = [(s, r) for s in BASELINES if (r := paper_ratio(s, task)) is not None]
    return min(ratios, key=lambda x: x[1]) if ratios else None


def _full(summary: dict, task: str) -> float | None:
    d = ((summary["tasks"][task]["signals"].get(FULL_TELEOP) or {}).get("default")) or {}
    return d.get("assisted_steps") or None


def _cell(point: dict | None, full: float | None, best: dict | None = None) -> str:
    """ratio, requests at 100%; else the best success and its ratio in brackets."""
    if point is not None and point["success_rate"] >= 1 - 1e-9 and full:
        return f"{point['assisted_steps'] / full:.2f}, {point['events']:.1f}"
    best = best or point
    if best is None:
        return "—"
    ratio = f": {best['assisted_steps'] / full:.2f}" if full else ""
    return f"— ({100 * best['success_rate']:.0f}%{ratio})"


def _best_any(row: dict) -> dict | None:
    """The point of a signal's sweep with the highest success, fewest steps among those."""
    points = (row.get("curve") or []) + ([row["default"]] if row.get("default") else [])
    return max(points, key=lambda p: (p["success_rate"], -p["assisted_steps"])) if points else None


def floor_cell(floor: dict, task: str) -> str:
    row = (floor.get("tasks") or {}).get(task)
    if not row:
        return "not run"
    chosen = row["floor"] or row["best"]
    e = chosen["eval"]
    if row["floor"]:
        return f"{e['ratio']:.2f}, {e['requests']:.1f}"
    return f"— ({100 * e['success_rate']:.0f}%: {e['ratio']:.2f}, {e['requests']:.1f})"


def markdown(summary: dict, floor: dict | None, default_signal: str | None) -> str:
    tasks = list(summary["tasks"])
    p = summary.get("provenance", {})
    lines = [
        "<!-- written by `hitl bench hitl --report --floor --default-signal`; do not edit by hand -->",
        "",
        "Assisted steps per episode at 100% success, as a ratio to full teleoperation on the same seeds, "
        "then requests per episode (4 operator steps each). `— (x%: r)`: 100% was not reached; the best "
        "success and its ratio.",
        "",
        "| | " + " | ".join(tasks) + " |",
        "|---|" + "---|" * len(tasks),
    ]
    cells = [f"{r:.2f}" if (r := paper_ratio(PAPER_METRIC, t)) is not None else "" for t in tasks]
    lines.append("| paper, its metric (Table I) | " + " | ".join(cells) + " |")
    cells = [f"{b[1]:.2f} (`{b[0]}`)" if (b := paper_best_baseline(t)) else "" for t in tasks]
    lines.append("| paper, its best baseline | " + " | ".join(cells) + " |")
    if floor is not None:
        lines.append(
            "| **floor** (oracle, best of its sweep) | " + " | ".join(floor_cell(floor, t) for t in tasks) + " |"
        )
    signals = sorted({s for t in tasks for s in summary["tasks"][t]["signals"]} - {FULL_TELEOP})
    if default_signal in signals:
        cells = []
        for t in tasks:
            row = summary["tasks"][t]["signals"].get(default_signal) or {}
            cells.append(_cell(row.get("default"), _full(summary, t)))
        lines.append(f"| **`{default_signal}`, the fleet's signal, as shipped** | " + " | ".join(cells) + " |")
    order = ([PAPER_METRIC] if PAPER_METRIC in signals else []) + [s for s in signals if s != PAPER_METRIC]
    for s in order:
        cells = []
        for t in tasks:
            row = summary["tasks"][t]["signals"].get(s)
            if row is None:
                cells.append("")
            elif row.get("skipped"):
                cells.append("n/a")
            else:
                cell = _cell(row.get("best_100"), _full(summary, t), _best_any(row))
                pending = row.get("pending") and row.get("best_100") is None
                cells.append(f"pending {cell}" if pending else cell)  # its sweep has cells still to run
        what = "the paper's metric, " if s == PAPER_METRIC else ""
        lines.append(f"| `{s}`, {what}best of its sweep | " + " | ".join(cells) + " |")
    full = [f"{f:.1f} steps" if (f := _full(summary, t)) else "" for t in tasks]
    lines.append("| full teleoperation | " + " | ".join(full) + " |")
    lines += [
        "",
        f"Seeds {p.get('seeds')}; `{p.get('command', '')}`; {p.get('machine', '')}; {p.get('date', '')}.",
    ]
    if summary.get("pending_cells"):
        lines.append(
            f"pending: {summary['pending_cells']} cells of the sweeps had not run when this was written; a cell "
            "marked so gives the best point so far (`--cached-only`, a run in progress)."
        )
    if floor is not None:
        fp = floor.get("provenance") or {}
        lines.append(f"Floor: `{fp.get('command', '')}`, {fp.get('date', '')}.")
    return "\n".join(lines)

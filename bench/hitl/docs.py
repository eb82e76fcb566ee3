"""The markdown and figures of a ``hitl bench hitl`` run (``--report docs/benchmarks/hitl.md``).

Figures (into ``--figures``): one success-vs-assisted-steps curve per task, and one timeline per task
showing where on the trajectory every signal fires in the shadow runs. Each figure's footer states
the command, seeds, machine and date.
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bench.hitl.report import PAPER  # noqa: E402
from bench.hitl.run import FULL_TELEOP, RANDOM, quantile_label, shadow_scores, thresholds_from  # noqa: E402
from bench.report_sections import replace_section  # noqa: E402

PAPER_COLUMN = {"lift-nut": "lift", "lift-hammer": "lift", "lift-hook": "lift"}
FIRE_QUANTILE = 0.95  # the timelines mark steps above this quantile of the reference scores


FOOTER_LINE_IN = 0.11  # height of one footer line (6 pt text) in inches


def _footer(fig, summary: dict) -> int:
    """Writes the provenance footer at the bottom of ``fig``; returns its number of lines."""
    p = summary.get("provenance", {})
    lines = [
        *textwrap.wrap(p.get("command", ""), 110),
        f"seeds {p.get('seeds')}, {p.get('machine', '')}, {p.get('date', '')}",
    ]
    fig.text(0.01, 0.005, "\n".join(lines), fontsize=6, color="0.35", va="bottom")
    return len(lines)


def _save(fig, summary: dict, path: Path, axis_room_in: float = 0.5) -> Path:
    """Adds the provenance footer, leaves ``axis_room_in`` inches above it for the x axis's ticks and
    label (so a long command never overlaps them), writes the figure and closes it."""
    n = _footer(fig, summary)
    height = fig.get_figheight()
    fig.subplots_adjust(bottom=(axis_room_in + FOOTER_LINE_IN * n) / height, top=1 - 0.4 / height)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_curves(summary: dict, out_dir: Path, prefix: str = "hitl") -> list[Path]:
    out = []
    for task, row in summary["tasks"].items():
        fig, ax = plt.subplots(figsize=(7, 4.6))
        if len(row["signals"]) > len(plt.get_cmap("tab10").colors):  # one colour per signal
            ax.set_prop_cycle(color=plt.get_cmap("tab20").colors)
        for s, r in sorted(row["signals"].items()):
            pts = r["curve"] + ([r["default"]] if r["default"] else [])
            if not pts:
                continue
            pts = sorted(pts, key=lambda p: p["assisted_steps"])
            x = [p["assisted_steps"] for p in pts]
            y = [100 * p["success_rate"] for p in pts]
            if s == FULL_TELEOP:
                ax.scatter(x, y, marker="*", s=120, color="black", label=s, zorder=5)
                continue
            style = "--" if s == RANDOM else "-"
            (line,) = ax.plot(x, y, style, marker="o", ms=3, lw=1.2, label=s)
            if r["default"]:
                d = r["default"]
                ax.scatter([d["assisted_steps"]], [100 * d["success_rate"]], marker="s", s=36, color=line.get_color())
        ax.set_xlabel("human-assisted steps per episode")
        ax.set_ylabel("success rate (%)")
        ax.set_ylim(-3, 103)
        ax.set_title(f"{task}: success vs assisted steps (threshold sweep; square: own calibration)", fontsize=9)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
        out.append(_save(fig, summary, out_dir / f"{prefix}-curve-{task}.png"))
    return out


def _fire_thresholds(raw: dict) -> dict[tuple[str, str], float]:
    """(policy, signal) -> the ``FIRE_QUANTILE`` of its scores on the policy's reference rollouts."""
    out = {}
    for policy, ref in raw["reference"].items():
        labels = {k for e in ref["episodes"] for k in e["scores"]}
        for s in labels:
            value = thresholds_from(shadow_scores(ref, s), (FIRE_QUANTILE,)).get(quantile_label(FIRE_QUANTILE))
            if value is not None and s not in (FULL_TELEOP, RANDOM):
                out[(policy, s)] = value
    return out


def plot_timelines(summary: dict, raw: dict, out_dir: Path, prefix: str = "hitl") -> list[Path]:
    """Per task: for every signal, the share of shadow episodes (the policy alone) whose score is above
    the signal's reference 95% quantile at each step, failed and successful episodes apart."""
    thresholds = _fire_thresholds(raw)
    policies = raw["recipe"]["policies"]
    out = []
    for task, shadow in raw["shadow"].items():
        eps = shadow["episodes"]
        signals = [s for s in sorted(eps[0]["scores"]) if (policies[task], s) in thresholds] if eps else []
        if not signals:
            continue
        horizon = max(len(e["scores"][signals[0]]) for e in eps)
        fig, axes = plt.subplots(len(signals), 1, figsize=(8, 1.1 * len(signals) + 1.2), sharex=True, squeeze=False)
        for ax, s in zip(axes[:, 0], signals, strict=True):
            thr = thresholds[(policies[task], s)]
            for success, colour in ((False, "tab:red"), (True, "tab:green")):
                group = [e for e in eps if e["success"] == success]
                if not group:
                    continue
                fired = np.full((len(group), horizon), np.nan)
                for i, e in enumerate(group):
                    v = np.asarray(e["scores"][s], dtype=np.float64)
                    fired[i, : len(v)] = v > thr
                with np.errstate(invalid="ignore"):  # steps after every episode of the group ended
                    share = np.nansum(fired, axis=0) / np.maximum((~np.isnan(fired)).sum(axis=0), 1)
                name = "failed" if not success else "succeeded"
                ax.plot(share, color=colour, lw=1, label=f"{name} ({len(group)})")
            ax.set_ylim(-0.05, 1.05)
            ax.set_ylabel(s, rotation=0, ha="right", fontsize=7)
            ax.tick_params(labelsize=6)
        axes[0, 0].legend(fontsize=6, loc="upper right")
        axes[0, 0].set_title(
            f"{task}: share of autonomous episodes where each signal fires (above its reference 95% quantile)",
            fontsize=8,
        )
        axes[-1, 0].set_xlabel("control step")
        fig.subplots_adjust(left=0.22, hspace=0.25)
        out.append(_save(fig, summary, out_dir / f"{prefix}-timeline-{task}.png"))
    return out


def _header(columns: list[str]) -> list[str]:
    """A markdown table's first two lines: a ``signal`` column, then ``columns``."""
    return ["| signal | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]


def _fmt(point: dict | None) -> str:
    return "—" if point is None else f"{point['assisted_steps']:.1f}"


def run_label(summary: dict, section: str) -> str:
    """What a section measured, for its headings: the section's name, then its signals, tasks and
    episodes per task (``main run: 10 signals, 5 tasks, 20 episodes each``). Every heading of a section
    ends with it, so two sections of one report never share a heading."""
    recipe = summary.get("recipe") or {}
    parts = [f"{len(recipe['signals'])} signals"] if recipe.get("signals") else []
    parts.append(f"{len(summary['tasks'])} tasks")
    if recipe.get("episodes"):
        parts.append(f"{recipe['episodes']} episodes each")
    return f"{section} run: " + ", ".join(parts)


def markdown(summary: dict, figures: list[Path], report: Path, paper: bool = True, section: str = "main") -> str:
    """The generated section; ``paper`` adds the paper's table beside ours (the main run's section).
    Every heading names the section and what it ran (``run_label``)."""
    tasks = list(summary["tasks"])
    p = summary.get("provenance", {})
    label = run_label(summary, section)
    lines = [
        "<!-- written by `hitl bench hitl --report`; do not edit by hand -->",
        "",
        f"Command: `{p.get('command', '')}`  ",
        f"Seeds {p.get('seeds')} (reference rollouts {p.get('reference_seeds')}); {p.get('machine', '')}; "
        f"{p.get('date', '')}; recipe {summary['recipe_hash']}.",
        "",
        f"### Fewest human-assisted steps per episode for 100% success (95% in brackets), {label}",
        "",
        *_header(tasks),
    ]
    signals = sorted({s for t in tasks for s in summary["tasks"][t]["signals"]})
    for s in signals:
        cells = []
        for t in tasks:
            r = summary["tasks"][t]["signals"].get(s)
            if r is None:
                cells.append("")
            elif r.get("skipped"):
                cells.append("n/a")
            elif r.get("pending") and r["best_100"] is None:
                cells.append(f"pending ({_fmt(r['best_95'])})")
            else:
                cells.append(f"{_fmt(r['best_100'])} ({_fmt(r['best_95'])})")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines += ["", "— : no threshold of the sweep reached that success rate."]
    reasons = {
        r["skipped"]: s
        for s in signals
        for t in tasks
        if (r := summary["tasks"][t]["signals"].get(s) or {}).get("skipped")
    }
    lines += [f"n/a ({s}): {why}" for why, s in reasons.items()]
    if summary.get("pending_cells"):
        lines.append(
            f"pending: {summary['pending_cells']} cells of the sweep had not run when this was written "
            "(a report of a run in progress, `--cached-only`)."
        )
    lines.append("")
    if paper:
        lines += [
            f"### The paper's table beside ours, {label}",
            "",
            "| signal | paper: Lift / Cup / Drawer | ours: " + " / ".join(tasks) + " |",
            "|---|---|---|",
        ]
        for s, row in PAPER.items():
            mine = []
            for t in tasks:
                r = summary["tasks"][t]["signals"].get(s)
                mine.append(_fmt(r["best_100"]) if r and not r.get("skipped") else "n/a")
            lines.append(
                f"| {s} | {row['lift']} / {row['cup-stack']} / {row['open-drawer']} | " + " / ".join(mine) + " |"
            )
        lines.append("")
    else:  # a short sweep (the ablations): every point of it, as the curves are too close to read
        lines += [f"### Every threshold of the sweep, {label}", "", *_header(tasks)]
        for s in signals:
            cells = []
            for t in tasks:
                r = summary["tasks"][t]["signals"].get(s) or {}
                cells.append(
                    "<br>".join(
                        f"{c['label']}: {100 * c['success_rate']:.0f}% / {c['assisted_steps']:.1f}"
                        for c in r.get("curve") or []
                    )
                )
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
        lines += ["", "Cells: threshold: success rate / assisted steps per episode.", ""]
    lines += [
        f"### At each signal's own calibration, {label}",
        "",
        *_header(tasks),
    ]
    for s in signals:
        cells = []
        for t in tasks:
            r = summary["tasks"][t]["signals"].get(s) or {}
            d = r.get("default")
            if d is not None:
                cells.append(f"{100 * d['success_rate']:.0f}% / {d['assisted_steps']:.1f}")
            else:
                cells.append("pending" if r.get("pending") and not r.get("skipped") else "n/a")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines += ["", "Cells: success rate / assisted steps per episode.", ""]
    fa = summary.get("false_alarms") or {}
    if fa.get("signals"):
        labels = sorted({lab for r in fa["signals"].values() for lab in r["by_threshold"]}, key=lambda x: float(x[1:]))
        lines += [
            f"### False alarms on {fa['task']} ({fa['episodes']} episodes that succeed on their own), {label}",
            "",
            "| signal | own calibration: steps | own calibration: episodes that ask | " + " | ".join(labels) + " |",
            "|---|---|---|" + "---|" * len(labels),
        ]
        for s, r in sorted(fa["signals"].items()):
            own = "—" if r["default"] is None else f"{100 * r['default']:.1f}%"
            eps = "—" if r.get("episodes_asking") is None else f"{100 * r['episodes_asking']:.0f}%"
            by = [f"{100 * r['by_threshold'][lab]:.1f}%" if lab in r["by_threshold"] else "" for lab in labels]
            lines.append(f"| {s} | {own} | {eps} | " + " | ".join(by) + " |")
        lines.append("")
    diag = summary.get("diagnostics") or {}
    if diag.get("tasks"):
        dt = list(diag["tasks"])
        lines += [
            f'### Per-state AUROC for "needs help" (last {diag["window"]} steps before an autonomous failure '
            f"vs every step of episodes the policy completes alone), {label}",
            "",
            *_header(dt),
        ]
        names = sorted({s for t in dt for s in diag["tasks"][t]["auroc"]})
        for s in names:
            vals = [diag["tasks"][t]["auroc"].get(s) for t in dt]
            lines.append(f"| {s} | " + " | ".join("—" if v is None else f"{v:.2f}" for v in vals) + " |")
        counts = ", ".join(f"{t} {diag['tasks'][t]['positives']}/{diag['tasks'][t]['negatives']}" for t in dt)
        lines += ["", f"States (positive/negative): {counts}.", ""]
        if any("auroc_floor" in diag["tasks"][t] for t in dt):
            lines += [
                f'### Per-state AUROC for "needs help" by the floor (the {summary["recipe"]["budget"]} states '
                "from the oracle's first request on, in episodes the policy fails alone and the oracle brings "
                f"through; negatives as above), {label}",
                "",
                *_header(dt),
            ]
            for s in names:
                vals = [(diag["tasks"][t].get("auroc_floor") or {}).get(s) for t in dt]
                lines.append(f"| {s} | " + " | ".join("—" if v is None else f"{v:.2f}" for v in vals) + " |")
            counts = ", ".join(
                f"{t} {diag['tasks'][t].get('floor_positives', 0)} in {diag['tasks'][t].get('floor_episodes', 0)} "
                "episodes"
                for t in dt
            )
            lines += ["", f"Positive states: {counts}.", ""]
        lines += [
            "### Where each score peaks (median step of its maximum over the autonomous episodes, and that "
            f"step as a share of the episode), {label}",
            "",
            *_header(dt),
        ]
        for s in names:
            cells = []
            for t in dt:
                p = diag["tasks"][t].get("peak_step", {}).get(s) or {}
                cells.append(f"{p['median_step']:.0f} ({100 * p['median_share']:.0f}%)" if p else "—")
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
        lines.append("")
    if figures:
        lines += [f"### Figures, {label}", ""]
        for f in figures:  # relative to the report, wherever the figures folder is (docs/figures/)
            rel = Path(os.path.relpath(Path(f).resolve(), report.parent.resolve())).as_posix()
            lines.append(f"![{Path(f).stem}]({rel})")
        lines.append("")
    return "\n".join(lines)


def write_report(summary: dict, raw: dict, report: Path, figures_dir: Path, section: str = "main") -> Path:
    """Writes the figures and the generated ``section`` of ``report``: the text between its markers
    is replaced and the hand-written text around them kept; a report without them gets them appended."""
    figures_dir.mkdir(parents=True, exist_ok=True)
    prefix = "hitl" if section == "main" else f"hitl-{section}"
    figures = plot_curves(summary, figures_dir, prefix) + plot_timelines(summary, raw, figures_dir, prefix)
    body = markdown(summary, figures, report, paper=section == "main", section=section)
    return replace_section(report, section, body)

"""The markdown table and figure of ``hitl bench finetune`` (a generated section of docs/benchmarks/finetune.md)."""

from __future__ import annotations

import os
from dataclasses import MISSING, fields
from pathlib import Path

import numpy as np

from bench.finetune.run import FULL, FinetuneBenchConfig
from policy.finetune import FinetuneConfig


def _rate(success: dict, tasks: list[str]) -> float:
    return float(np.mean([success[t]["success_rate"] for t in tasks]))


def summarize(result: dict) -> dict:
    """Per source: samples -> (training-object success, unseen-object success), means over the repeats,
    and the unseen-object success of each repeat; the goal's verdict (on the means)."""
    cfg = result["config"]
    train, unseen = [cfg["train_task"]], list(cfg["unseen"])
    pre = result["pretrained"]
    rates: dict[str, dict[int, list[tuple[float, float]]]] = {}
    for p in result["points"]:
        if "success" in p:
            rate = (_rate(p["success"], train), _rate(p["success"], unseen))
            rates.setdefault(p["source"], {}).setdefault(p["samples"], []).append(rate)
    curves = {
        s: {k: (float(np.mean([r[0] for r in v])), float(np.mean([r[1] for r in v]))) for k, v in by_k.items()}
        for s, by_k in rates.items()
    }
    repeats = {s: {k: [r[1] for r in v] for k, v in by_k.items()} for s, by_k in rates.items()}
    base_unseen = _rate(pre, unseen)
    default = next((s for s in cfg["sources"] if s.startswith("takeover:")), None)  # the first listed
    verdict = None
    if default in curves and FULL in curves:
        small = {k: v for k, v in curves[default].items() if k <= 100}
        best_k = max(small, key=lambda k: small[k][1]) if small else None
        if best_k is not None:
            lift = small[best_k][1] - base_unseen
            full = curves[FULL].get(best_k, (None, None))[1]
            verdict = {
                "source": default,
                "samples": best_k,
                "unseen_lift": lift,
                "lift_goal_met": lift >= 0.4,
                "full_trajectory_at_same_count": full,
                "beats_full_trajectory": full is not None and small[best_k][1] > full,
            }
    return {
        "pretrained": {"train": _rate(pre, train), "unseen": base_unseen},
        "curves": curves,
        "unseen_by_repeat": repeats,
        "verdict": verdict,
    }


def plot(summary: dict, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, which, title in ((axes[0], 1, "unseen objects"), (axes[1], 0, "training object (lift-cube)")):
        for source, curve in sorted(summary["curves"].items()):
            ks = sorted(curve)
            (line,) = ax.plot(ks, [curve[k][which] for k in ks], marker="o", label=source)
            each = summary.get("unseen_by_repeat", {}).get(source, {})
            if which and any(len(each.get(k, [])) > 1 for k in ks):  # the repeats' range
                lo, hi = ([f(each[k]) for k in ks] for f in (min, max))
                ax.fill_between(ks, lo, hi, color=line.get_color(), alpha=0.2, linewidth=0)
        base = summary["pretrained"]["unseen" if which else "train"]
        ax.axhline(base, color="grey", linestyle="--", label="pretrained")
        ax.set_xlabel("fine-tuning samples")
        ax.set_title(title)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("autonomous success")
    axes[1].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _mix(cfg: dict) -> str:
    """The mini-batch mix, takeover/pretraining in percent (``50/50`` by default)."""
    ratio = cfg.get("finetune", {}).get("ratio", 0.5)
    return f"{round(100 * ratio)}/{round(100 * (1 - ratio))}"


def _first_close_table(result: dict) -> list[str]:
    """Where the evaluated policies first closed the gripper on the unseen objects (points evaluated
    before this was recorded have nothing to show and are left out)."""
    unseen = list(result["config"]["unseen"])
    repeated = result["config"].get("repeats", 1) > 1
    rows = [("pretrained", 0, result["pretrained"])] + [
        (p["source"] + (f", repeat {p.get('repeat', 0)}" if repeated else ""), p["samples"], p["success"])
        for p in result["points"]
        if "success" in p
    ]
    rows = [r for r in rows if all((r[2][t].get("first_close") or {}).get("episodes") for t in unseen)]
    if not rows:
        return []

    def cm(fc: dict, key: str) -> str:
        return "-" if fc[key] is None else f"{100 * fc[key]:.1f}"

    lines = [
        f"Where the gripper first closes on the unseen objects (per task: {', '.join(unseen)}): the episodes "
        "that close it, and the median distance in the plane from the object's grasp point and from its body "
        "origin, where a cube is grasped.",
        "",
        "| source | samples | episodes that close | from the grasp point (cm) | from the body origin (cm) |",
        "|---|---|---|---|---|",
    ]
    for source, k, success in rows:
        fcs = [success[t]["first_close"] for t in unseen]
        closed = " / ".join(f"{f['closed']}/{f['episodes']}" for f in fcs)
        lines.append(
            f"| {source} | {k} | {closed} "
            f"| {' / '.join(cm(f, 'median_to_grasp_m') for f in fcs)} "
            f"| {' / '.join(cm(f, 'median_to_origin_m') for f in fcs)} |"
        )
    return [*lines, ""]


def _hand_back(cfg: dict) -> str:
    if cfg["hand_back"] == "budgeted":
        return f"budgeted hand-back ({cfg['budget']} operator steps per request), "
    if cfg["hand_back"] == "operator":
        return "the operator hands back once the object is held, "
    return f"continuous hand-back (back after {cfg.get('return_after', 1)} calm step(s)), "


def _selection(cfg: dict) -> str:
    """The takeover selection of the recipe, in words ('' when every step of every takeover is used)."""
    ft = cfg.get("finetune", {})
    parts = ["only takeovers in episodes that succeeded"] if ft.get("successful_only") else []
    if ft.get("takeover_tail") is not None:
        parts.append(
            f"of each takeover only its last {ft['takeover_tail']} steps, those that led to the hand-back "
            "(a takeover cut to fit K keeps its last steps)"
        )
    return f" Takeover sources keep {'; '.join(parts)}." if parts else ""


def _defaults(cls) -> dict:
    return {f.name: f.default for f in fields(cls) if f.default is not MISSING}


def heading(section: str, result: dict) -> str:
    """The section's heading: its name, then what it measured: the sources and counts, and every
    setting that differs from the bench's and the job's defaults (policy, hand-back, evaluation
    episodes, stride, recipe, takeover selection, repeats). Unique within a report, since a report's
    sections have unique names."""
    cfg = result["config"]
    bench = _defaults(FinetuneBenchConfig)
    job = _defaults(FinetuneConfig)
    ft = {**job, **(cfg.get("finetune") or {})}
    counts = ", ".join(str(k) for k in cfg.get("counts", ()))
    parts = [f"{', '.join(cfg.get('sources', ()))} at K = {counts}"]
    if cfg.get("policy", bench["policy"]) != bench["policy"]:
        parts.append(f"policy {cfg['policy']}")
    hand_back = cfg.get("hand_back", bench["hand_back"])
    if hand_back == "budgeted":
        parts.append(f"budgeted hand-back of {cfg.get('budget', bench['budget'])} steps")
    elif hand_back == "operator":
        parts.append("the operator hands back once the object is held")
    elif cfg.get("return_after", bench["return_after"]) != bench["return_after"]:
        parts.append(f"hand-back after {cfg['return_after']} calm steps")
    if cfg.get("eval_episodes", bench["eval_episodes"]) != bench["eval_episodes"]:
        parts.append(f"{cfg['eval_episodes']} episodes per task")
    if cfg.get("stride", bench["stride"]) != bench["stride"]:
        parts.append(f"one step in {cfg['stride']}")
    if ft["ratio"] != job["ratio"]:
        parts.append(f"takeover share {ft['ratio']:g}")
    if ft["lr"] != job["lr"]:
        parts.append(f"learning rate {ft['lr']:g}")
    if ft["steps"] != job["steps"]:
        parts.append(f"{ft['steps']} training steps")
    if ft["widen_obs_range"] != job["widen_obs_range"]:
        parts.append("the parent's observation range")
    if ft["successful_only"]:
        parts.append("successful episodes only")
    if ft["takeover_tail"] is not None:
        parts.append(f"the last {ft['takeover_tail']} steps of each takeover")
    if cfg.get("repeats", bench["repeats"]) != bench["repeats"]:
        parts.append(f"{cfg['repeats']} repeats")
    return f"## {section}: " + "; ".join(parts)


def markdown(
    result: dict, summary: dict, figure: Path | None, report: Path, command: str, section: str = "finetune"
) -> str:
    cfg = result["config"]
    repeats = cfg.get("repeats", 1)
    extra = (" unseen, each repeat |", "---|", " - |") if repeats > 1 else ("", "", "")
    unseen = ", ".join(cfg["unseen"])
    lines = [
        heading(section, result),
        "",
        f"Generated by `{command}` ({result['seconds']:.0f} s; {result['read_from_cache']} of "
        f"{result['read_from_cache'] + result['computed_in_this_run']} evaluations read from the cache of an "
        f"earlier run). Policy `{result['policy']}` (trained on "
        f"{result['trained_on']}); unseen objects: {unseen}. Each point fine-tunes the same pretrained weights "
        f"on the first K samples of its source (K/{len(cfg['unseen'])} per unseen task) with {_mix(cfg)} mini-batches "
        f"against the pretraining set, then rolls out {cfg['eval_episodes']} seeded episodes per task "
        f"(seeds from {cfg['eval_seed']}) through the controller. Takeover data: the scripted expert as operator, "
        + _hand_back(cfg)
        + f"cooldown {cfg['cooldown']}."
        + (
            f" Every source is subsampled: one step in {cfg['stride']} of each takeover or demonstration."
            if cfg.get("stride", 1) > 1
            else ""
        )
        + _selection(cfg),
        "",
        "Recorded steps: the steps of the takeovers (or demonstrations) the K samples were drawn from, whole, "
        "with the ones left out on the way: what the samples cost the operator (or the expert). Steps: "
        "training steps."
        + (
            f" Each point is repeated {repeats} times (repeat r > 0: the runs drawn in another seeded order, "
            "fine-tuning seed + r); success rates are means over the repeats, the last column gives "
            "each repeat's unseen-object success, and the figure shades their range."
            if repeats > 1
            else ""
        ),
        "",
        "| source | samples | recorded steps | training object | unseen objects | steps |" + extra[0],
        "|---|---|---|---|---|---|" + extra[1],
        f"| pretrained | 0 | - | {summary['pretrained']['train']:.2f} | {summary['pretrained']['unseen']:.2f} | - |"
        + extra[2],
    ]
    rows: dict[tuple[str, int], list[dict]] = {}
    for p in result["points"]:
        rows.setdefault((p["source"], p["samples"]), []).append(p)
    for (source, k), ps in rows.items():
        done = [p for p in ps if "success" in p]
        recorded = [p["recorded_steps"] for p in ps if "recorded_steps" in p]
        shown = round(float(np.mean(recorded))) if recorded else "-"
        if not done:
            lines.append(f"| {source} | {k} | {shown} | - | - | {ps[0].get('error', '')} |" + extra[2])
            continue
        tr, un = summary["curves"][source][k]
        each = " / ".join(f"{u:.2f}" for u in summary["unseen_by_repeat"][source][k])
        lines.append(
            f"| {source} | {k} | {shown} | {tr:.2f} | {un:.2f} | {done[0]['steps']} |"
            + (f" {each} |" if extra[0] else "")
        )
    lines.append("")
    lines += _first_close_table(result)
    lines += [
        "| source | takeovers (or episodes) per task | samples per task | gripper closed in |",
        "|---|---|---|---|",
    ]
    for source, c in result["collected"].items():
        tasks = list(c["samples"])
        closed = " / ".join(format(c["gripper_closed_share"][t], ".0%") for t in tasks)
        ok = c.get("in_successful_episodes")
        runs = " / ".join(str(c["takeovers"][t]) + (f" ({ok[t]} successful)" if ok else "") for t in tasks)
        lines.append(
            f"| {source} | {runs} | {' / '.join(str(c['samples'][t]) for t in tasks)} | {closed} of the samples |"
        )
    lines.append(f"\n(per task: {', '.join(cfg['unseen'])})\n")
    if result["skipped_sources"]:
        lines.append("Sources not run (their signal is not trained next to this policy):")
        lines += [f"- `{s}`: {why}" for s, why in result["skipped_sources"].items()]
        lines.append("")
    v = summary["verdict"]
    if v:
        lines.append(
            f"**Goal** (takeover data with ≤ 100 samples lifts unseen-object success by ≥ 0.4 and beats "
            f"full-trajectory data at the same count), for `{v.get('source', 'takeover:spread')}`: at K = "
            f"{v['samples']}, unseen success "
            f"{summary['pretrained']['unseen']:.2f} → {summary['pretrained']['unseen'] + v['unseen_lift']:.2f} "
            f"(+{v['unseen_lift']:.2f}, {'met' if v['lift_goal_met'] else 'not met'}); full-trajectory at that "
            f"count: {v['full_trajectory_at_same_count']:.2f} "
            f"({'beaten' if v['beats_full_trajectory'] else 'not beaten'})."
        )
        lines.append("")
    if figure is not None:
        lines.append(f"![fine-tuning curves]({os.path.relpath(figure, report.parent)})")
        lines.append("")
    return "\n".join(lines)

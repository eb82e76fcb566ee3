"""The figure of ``hitl bench operators``: success per task, episodes finished per robot of each task and the
queue's wait against the fleet's size, one line style per run (today's and, for comparison, an earlier one),
the headline's limits dashed. A success rate over one or two episodes says little: the middle panel shows how
many there were."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from bench.operators import SUCCESS_MIN, WAIT_MAX_TICKS, WAIT_P95_MAX_TICKS  # noqa: E402

TASK_COLOURS = {
    "lift-cube": "tab:blue",
    "lift-hammer": "tab:orange",
    "cup-stack": "tab:green",
    "open-drawer": "tab:red",
}
STYLES = ("-", "--", ":")


def plot_operators(runs: list[tuple[str, dict]], out: Path) -> Path:
    """runs: (label, ``run_operators`` report) pairs, drawn in that order."""
    fig, (ok, done, wait) = plt.subplots(1, 3, figsize=(15, 4.4))
    for k, (label, report) in enumerate(runs):
        style = STYLES[k % len(STYLES)]
        sizes = report["sizes"]
        x = [s["robots"] for s in sizes]
        tasks = list(report["plan"]["mix"])
        for task in tasks:
            pts = [(s["robots"], s["per_task"][task]["success_rate"]) for s in sizes if task in s["per_task"]]
            pts = [(n, r) for n, r in pts if r is not None]
            if pts:
                n, rate = zip(*pts, strict=True)
                ok.plot(n, rate, style, marker="o", color=TASK_COLOURS.get(task), label=f"{task} ({label})")
            per_robot = [
                (s["robots"], s["per_task"][task]["episodes"] / s["per_task"][task]["robots"])
                for s in sizes
                if task in s["per_task"] and "episodes" in s["per_task"][task]
            ]
            if per_robot:
                n, count = zip(*per_robot, strict=True)
                done.plot(n, count, style, marker="o", color=TASK_COLOURS.get(task), label=f"{task} ({label})")
        p95 = [s["queue_wait"]["p95_ticks"] for s in sizes]
        most = [s["queue_wait"]["max_ticks"] for s in sizes]
        wait.plot(x, p95, style, marker="o", color="black", label=f"p95 ({label})")
        wait.plot(x, most, style, marker="s", color="tab:gray", label=f"max ({label})")
        best = report.get("robots_per_operator")
        if best is not None:
            wait.axvline(best, color="tab:green", ls=style, lw=1, label=f"robots per operator: {best} ({label})")
    ok.axhline(SUCCESS_MIN, color="tab:red", ls="--", lw=0.8)
    ok.set(xlabel="robots in the fleet (one operator)", ylabel="success rate", ylim=(0, 1.05), title="Success per task")
    done.set(
        xlabel="robots in the fleet (one operator)",
        ylabel="episodes ended per robot",
        yscale="symlog",
        title="Episodes finished in the run, per robot",
    )
    wait.axhline(WAIT_P95_MAX_TICKS, color="black", ls="--", lw=0.8)
    wait.axhline(WAIT_MAX_TICKS, color="tab:gray", ls="--", lw=0.8)
    wait.set(xlabel="robots in the fleet (one operator)", ylabel="control ticks", title="Queue wait, request to claim")
    ok.legend(fontsize=6)
    wait.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out

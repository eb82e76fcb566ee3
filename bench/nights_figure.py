"""The figure of ``hitl bench nights``: human effort per episode and success over the days, per task."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

PANELS = (
    ("assisted_steps_per_episode", "assisted steps per episode"),
    ("operator_seconds_per_episode", "operator time per episode (s)"),
    ("autonomous_success", "autonomous success (asked nothing)"),
    ("success_with_help", "success with help"),
)


def plot_nights(report: dict, out: Path) -> Path:
    """Four panels over the days, a line per task; nights between the days are marked with the
    versions they promoted."""
    days = report["days"]
    x = [d["day"] for d in days]
    tasks = list(days[0]["per_task"])
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), sharex=True)
    for ax, (key, label) in zip(axes.flat, PANELS, strict=True):
        for task in tasks:
            y = [d["per_task"][task][key] for d in days]
            ax.plot(x, [float("nan") if v is None else v for v in y], marker="o", label=task)
        ax.set_title(label, fontsize=10)
        ax.set_xticks(x, [f"day {i}" for i in x])
        for night in report["nights"]:
            ax.axvline(night["night"] + 0.5, color="grey", lw=0.8, ls=":")
        if key in ("autonomous_success", "success_with_help"):
            ax.set_ylim(-0.05, 1.05)
    for night in report["nights"]:
        promoted = [j["version"] for j in night["jobs"] if j["promoted"]]
        axes[0, 0].annotate(
            "night {}: {}".format(night["night"], ", ".join(promoted) or "nothing promoted"),
            (night["night"] + 0.5, 1.0),
            xycoords=("data", "axes fraction"),
            fontsize=7,
            rotation=90,
            va="top",
            ha="right",
        )
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("hitl bench nights: effort and success per day (nights fine-tune between the days)", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out

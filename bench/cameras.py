"""``hitl bench cameras``: what rendering the policy's cameras costs per control step, with MuJoCo's defaults
and as served (``sim.vision.fast_model``), over an expert's episode of each task; and a figure of what the
policy sees (``--figure``)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.registry import make_expert, make_task
from sim.vision import PolicyCameras

TASKS = ("lift-cube", "lift-hammer", "cup-stack", "open-drawer")


@dataclass(frozen=True)
class CameraBench:
    tasks: tuple[str, ...] = TASKS
    seed: int = 0
    steps: int = 60  # control steps of the expert's episode, each rendered both ways
    frames_at: tuple[float, ...] = (0.0, 0.5)  # the figure's moments, as shares of those steps

    def __post_init__(self) -> None:
        for task in self.tasks:
            make_task(task)  # KeyError naming the registered tasks
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")


def bench_cameras(plan: CameraBench, progress: bool = True) -> tuple[dict, dict[str, list[dict[str, np.ndarray]]]]:
    """Per task: ms per control step of rendering all its policy cameras both ways (median over the episode's
    steps), and the views at ``frames_at`` for the figure."""
    from tqdm import tqdm

    rows, views = [], {}
    for name in tqdm(plan.tasks, desc="cameras", disable=not progress):
        task, expert = make_task(name), make_expert(name)
        task.reset(plan.seed)
        expert.reset(task, np.random.default_rng([plan.seed, 2]))
        model, data = task.mj_model(), task.mj_data()
        fast, default = PolicyCameras(model, task.cameras), PolicyCameras(model, task.cameras, fast=False)
        at = {min(plan.steps - 1, int(share * plan.steps)) for share in plan.frames_at}
        times: dict[str, list[float]] = {"default": [], "served": []}
        views[name] = []
        try:
            for t in range(plan.steps):
                for label, rig in (("default", default), ("served", fast)):
                    t0 = time.perf_counter()
                    images = rig.render(data)
                    times[label].append(time.perf_counter() - t0)
                if t in at:
                    views[name].append(images)  # the served views
                task.step(task.teleop(expert.act(task)).action)
        finally:
            fast.close()
            default.close()
            task.close()
        default_ms, served_ms = (1000 * float(np.median(times[k])) for k in ("default", "served"))
        rows.append(
            {
                "task": name,
                "cameras": [s.to_json() for s in task.cameras],
                "default_ms_per_step": round(default_ms, 2),
                "served_ms_per_step": round(served_ms, 2),
                "speedup": round(default_ms / served_ms, 1),
                "steps": plan.steps,
            }
        )
    return {"seed": plan.seed, "tasks": rows}, views


def plot_policy_views(views: dict[str, list[dict[str, np.ndarray]]], path: Path) -> Path:
    """One row per task and moment: each of its cameras as the policy sees it (the centre crop)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(task, k, frame) for task, frames in views.items() for k, frame in enumerate(frames)]
    cols = max(len(frame) for _, _, frame in rows)
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.0 * cols, 2.0 * len(rows)), squeeze=False)
    crops = {task: {s.name: s.crop for s in make_task(task).cameras} for task in views}
    for r, (task, k, frame) in enumerate(rows):
        for c in range(cols):
            ax = axes[r][c]
            ax.axis("off")
            if c >= len(frame):
                continue
            cam, image = list(frame.items())[c]
            ax.imshow(_centre_crop(image, crops[task][cam]), interpolation="nearest")
            ax.set_title(f"{task} · {cam}" + (" (later)" if k else ""), fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _centre_crop(image: np.ndarray, crop: int) -> np.ndarray:
    h, w = image.shape[:2]
    top, left = (h - crop) // 2, (w - crop) // 2
    return image[top : top + crop, left : left + crop]

"""``hitl experts``: the scripted experts' success on each task, measured without recording, and the
markdown table ``make docs`` writes to docs/experts.md."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from tqdm import tqdm

from sim.registry import make_expert, make_task
from sim.rollout import run_expert_episode


@dataclass(frozen=True)
class ExpertScore:
    task: str
    expert: str
    episodes: int
    successes: int
    mean_steps: float
    horizon: int
    first_seed: int
    failed_seeds: tuple[int, ...]

    @property
    def rate(self) -> float:
        return self.successes / self.episodes


def score_expert(
    task_name: str, episodes: int, seed: int = 1000, progress: bool = True, position: int = 0
) -> ExpertScore:
    """Runs the expert on seeds ``seed ..`` without recording and counts successes."""
    task, expert = make_task(task_name), make_expert(task_name)
    steps, failed = [], []
    try:
        for s in tqdm(
            range(seed, seed + episodes),
            desc=f"expert {task_name}",
            unit="ep",
            disable=not progress,
            position=position,
            leave=True,
        ):
            r = run_expert_episode(task, expert, s)
            steps.append(r.steps)
            if not r.success:
                failed.append(s)
    finally:
        task.close()
    return ExpertScore(
        task_name,
        expert.name,
        episodes,
        episodes - len(failed),
        sum(steps) / len(steps),
        task.horizon,
        seed,
        tuple(failed),
    )


def _score_job(args: tuple) -> ExpertScore:
    return score_expert(*args)


def score_experts(
    tasks: list[str], episodes: int, seed: int = 1000, workers: int = 2, progress: bool = True
) -> list[ExpertScore]:
    """Scores several experts, one process per task (robosuite is single-threaded)."""
    jobs = [(t, episodes, seed, progress, i) for i, t in enumerate(tasks)]
    if workers <= 1:
        return [_score_job(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(_score_job, jobs))


def expert_table(scores: list[ExpertScore], command: str) -> str:
    lines = [
        "# Scripted expert success",
        "",
        f"Measured with `{command}` (seeds {scores[0].first_seed}..{scores[0].first_seed + scores[0].episodes - 1}"
        " per task, distinct from the demonstration seeds). Target: >= 95% per task.",
        "",
        "| task | expert | success | rate | mean steps | horizon | failed seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        failed = ", ".join(map(str, s.failed_seeds)) or "-"
        lines.append(
            f"| `{s.task}` | {s.expert} | {s.successes}/{s.episodes} | {100 * s.rate:.0f}% | "
            f"{s.mean_steps:.1f} | {s.horizon} | {failed} |"
        )
    return "\n".join(lines) + "\n"

"""Recording scripted demonstrations and measuring expert success."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from sim.registry import make_expert, make_task
from sim.rollout import ExecutionNoise, StepRecord, run_expert_episode
from sim.spaces import ACTION_LABELS
from storage import keys
from storage.episodes import EpisodeWriter


def episode_path(out: Path, task: str, seed: int) -> Path:
    return Path(out) / f"{task}_seed{seed:06d}.mcap"


def record_demos(
    task_name: str,
    episodes: int,
    out: str | Path,
    seed: int = 0,
    progress: bool = True,
    noise: ExecutionNoise | None = None,
) -> tuple[list[Path], int]:
    """Writes ``episodes`` expert episodes (seeds ``seed .. seed + episodes - 1``), one MCAP file each.

    ``noise`` perturbs the executed actions (DART); the files hold the expert's clean actions.
    Returns the files and how many episodes succeeded.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    task, expert = make_task(task_name), make_expert(task_name)
    paths: list[Path] = []
    bar = tqdm(range(seed, seed + episodes), desc=f"demos {task_name}", unit="ep", disable=not progress)
    successes = 0
    try:
        for s in bar:
            path = episode_path(Path(out), task_name, s)
            task.reset(s)  # so that the metadata (e.g. the intended drawer) is this episode's; ~50 ms
            meta = task.metadata() | {
                "seed": s,
                "expert": expert.name,
                "obs_labels": _labels(task),
                "action_labels": list(ACTION_LABELS),
                "source": keys.SOURCE_EXPERT,
                "execution_noise": {"pos": noise.pos, "rot": noise.rot} if noise else None,
            }
            with EpisodeWriter(path, meta, object_names=list(task.object_poses())) as writer:

                def on_step(r: StepRecord, w: EpisodeWriter = writer) -> None:
                    w.write_step(
                        r.t, r.obs, r.action, r.ee_pos, r.ee_quat, r.gripper, r.success, keys.SOURCE_EXPERT, r.objects
                    )

                result = run_expert_episode(task, expert, s, on_step, noise)
                writer.finish(result.success, result.steps, "success" if result.success else "horizon")
            successes += result.success
            paths.append(path)
            bar.set_postfix(success=f"{successes}/{len(paths)}")
    finally:
        task.close()
    return paths, successes


def _labels(task) -> list[str]:
    out = []
    for name, n in task.obs_spec.parts:
        out += [name] if n == 1 else [f"{name}[{i}]" for i in range(n)]
    return out


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

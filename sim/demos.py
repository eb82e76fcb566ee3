"""Recording scripted demonstrations (the scripted experts' success is measured in ``lab.experts``)."""

from __future__ import annotations

import json
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm

from sim.registry import make_expert, make_task
from sim.rollout import ExecutionNoise, StepRecord, run_expert_episode
from sim.spaces import ACTION_LABELS
from storage import keys
from storage.episodes import EpisodeWriter
from storage.paths import portable

RECIPE_FILE = "recipe.json"  # in a folder of demonstrations: how to record it again


def episode_path(out: Path, task: str, seed: int) -> Path:
    return Path(out) / f"{task}_seed{seed:06d}.mcap"


@dataclass(frozen=True)
class DemoRecipe:
    """How a folder of demonstrations was recorded: enough to record it again, seed for seed, on
    another machine. ``record_demos`` writes it into the folder; ``hitl train`` copies it into the
    policy's config.json, so that a fine-tuning job can re-create its pretraining data."""

    task: str
    episodes: int
    seed: int = 0
    pos_noise: float = 0.0
    rot_noise: float = 0.0
    images: bool = False  # as a policy that sees cameras observes (``make_task(..., images=True)``): frames recorded

    def __post_init__(self) -> None:
        if not (isinstance(self.task, str) and self.task):
            raise ValueError(f"recipe: task must be a task name, got {self.task!r}")
        for name in ("episodes", "seed"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= (1 if name == "episodes" else 0)):
                raise ValueError(f"recipe: {name} must be an integer >= {1 if name == 'episodes' else 0}, got {v!r}")
        for name in ("pos_noise", "rot_noise"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"recipe: {name} must be a number >= 0, got {v!r}")
        if not isinstance(self.images, bool):
            raise ValueError(f"recipe: images must be true or false, got {self.images!r}")

    @classmethod
    def from_dict(cls, d: dict) -> DemoRecipe:
        if not isinstance(d, dict):
            raise ValueError(f"recipe: expected an object, got {type(d).__name__}")
        unknown = set(d) - {"task", "episodes", "seed", "pos_noise", "rot_noise", "images", "command"}
        if unknown:
            raise ValueError(f"recipe: unknown fields {sorted(unknown)}")
        try:
            return cls(**{k: v for k, v in d.items() if k != "command"})
        except TypeError as exc:
            raise ValueError(f"recipe: {exc}") from None

    @property
    def noise(self) -> ExecutionNoise | None:
        return ExecutionNoise(self.pos_noise, self.rot_noise) if self.pos_noise or self.rot_noise else None

    def files(self, folder: str | Path) -> list[Path]:
        return [episode_path(Path(folder), self.task, s) for s in range(self.seed, self.seed + self.episodes)]

    def command(self, out: str) -> str:
        """The ``hitl demos`` command line that records this recipe into ``out``."""
        noise = f" --pos-noise {self.pos_noise:g} --rot-noise {self.rot_noise:g}" if self.noise else ""
        images = " --images" if self.images else ""
        return f"hitl demos --task {self.task} --episodes {self.episodes} --seed {self.seed}{noise}{images} --out {out}"

    def to_dict(self) -> dict:
        return asdict(self)


def read_recipe(folder: str | Path) -> DemoRecipe | None:
    """The recipe ``record_demos`` left in ``folder``; None for a folder without one (recorded before
    recipes, or not by ``hitl demos``)."""
    path = Path(folder) / RECIPE_FILE
    if not path.is_file():
        return None
    return DemoRecipe.from_dict(json.loads(path.read_text()))


def ensure_demos(recipe: DemoRecipe, folder: str | Path, progress: bool = True, workers: int = 1) -> list[Path]:
    """Records, seeded as ``recipe`` says, the episodes of ``recipe`` that ``folder`` lacks (all of them
    on a fresh machine); returns the files it recorded (none when the folder is complete).

    The episodes are recorded into a sibling folder and moved in one by one when all are written, so
    a run that is interrupted leaves no half-written episode in ``folder``; the next call records what
    is still missing. ``workers`` > 1 records that many shares of the seeds in as many processes
    (robosuite is single-threaded; each episode depends on its seed alone, so the files are the same)."""
    folder = Path(folder)
    missing = [f for f in recipe.files(folder) if not f.is_file()]
    if not missing:
        return []
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    staging = folder.with_name(f".{folder.name}.recording")
    shutil.rmtree(staging, ignore_errors=True)
    seeds = sorted(int(f.stem.rsplit("seed", 1)[1]) for f in missing)
    size = -(-len(seeds) // workers)  # consecutive shares: one task per run of seeds
    shares = [seeds[i : i + size] for i in range(0, len(seeds), size)]
    jobs = [(recipe, staging, run, progress and i == 0) for i, share in enumerate(shares) for run in _runs(share)]
    try:
        if len(shares) == 1:
            for job in jobs:
                _record_run(job)
        else:
            import multiprocessing

            with ProcessPoolExecutor(len(shares), mp_context=multiprocessing.get_context("spawn")) as pool:
                list(pool.map(_record_run, jobs))
        folder.mkdir(parents=True, exist_ok=True)
        for f in missing:
            os.replace(staging / f.name, f)
        if not (folder / RECIPE_FILE).is_file():
            _write_recipe(folder, recipe)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return missing


def _record_run(job: tuple[DemoRecipe, Path, tuple[int, int], bool]) -> None:
    """One run of consecutive seeds (first, count) of ``recipe`` into ``staging``: a process's share."""
    recipe, staging, (lo, n), progress = job
    record_demos(
        recipe.task, n, staging, seed=lo, progress=progress, noise=recipe.noise, recipe=False, images=recipe.images
    )


def _runs(seeds: list[int]) -> list[tuple[int, int]]:
    """Consecutive seeds as (first, count) runs."""
    out: list[tuple[int, int]] = []
    for s in seeds:
        if out and out[-1][0] + out[-1][1] == s:
            out[-1] = (out[-1][0], out[-1][1] + 1)
        else:
            out.append((s, 1))
    return out


def _write_recipe(folder: Path, recipe: DemoRecipe) -> None:
    doc = recipe.to_dict() | {"command": recipe.command(portable(folder))}
    (folder / RECIPE_FILE).write_text(json.dumps(doc, indent=2) + "\n")


def record_demos(
    task_name: str,
    episodes: int,
    out: str | Path,
    seed: int = 0,
    progress: bool = True,
    noise: ExecutionNoise | None = None,
    recipe: bool = True,
    images: bool = False,
) -> tuple[list[Path], int]:
    """Writes ``episodes`` expert episodes (seeds ``seed .. seed + episodes - 1``), one MCAP file each.

    ``noise`` perturbs the executed actions (DART); the files hold the expert's clean actions. With
    ``recipe``, the folder's ``recipe.json`` records how to record it again (``DemoRecipe``); a folder
    that already holds other episodes keeps no recipe, since no single one made it. ``images``: the
    task observes as a policy that sees cameras does (``make_task(..., images=True)``): the observation
    is the robot's own state and every step carries its cameras' frames.
    Returns the files and how many episodes succeeded.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    out = Path(out)
    others = list(out.glob(keys.EPISODE_GLOB)) if out.is_dir() else []
    task, expert = make_task(task_name, images=images), make_expert(task_name)
    cameras = [c.to_json() for c in task.cameras] if images else []
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
                "obs_labels": task.obs_spec.labels(),
                "action_labels": list(ACTION_LABELS),
                "source": keys.SOURCE_EXPERT,
                "execution_noise": {"pos": noise.pos, "rot": noise.rot} if noise else None,
            }
            with EpisodeWriter(path, meta, object_names=list(task.object_poses()), cameras=cameras) as writer:

                def on_step(r: StepRecord, w: EpisodeWriter = writer) -> None:
                    w.write_step(
                        r.t,
                        r.obs,
                        r.action,
                        r.ee_pos,
                        r.ee_quat,
                        r.gripper,
                        r.success,
                        keys.SOURCE_EXPERT,
                        r.objects,
                        images=r.images,
                    )

                result = run_expert_episode(task, expert, s, on_step, noise)
                writer.finish(result.success, result.steps, "success" if result.success else "horizon")
            successes += result.success
            paths.append(path)
            bar.set_postfix(success=f"{successes}/{len(paths)}")
    finally:
        task.close()
    if recipe:
        made = DemoRecipe(task_name, episodes, seed, noise.pos if noise else 0.0, noise.rot if noise else 0.0, images)
        ours = set(made.files(out))
        if any(p not in ours for p in others):
            (out / RECIPE_FILE).unlink(missing_ok=True)
        else:
            _write_recipe(out, made)
    return paths, successes

"""``hitl bench finetune-load``: the fleet's control rate while a fine-tuning job runs beside it.

The real service (``LocalService``) with a fleet of autonomous robots; the control rate is measured
before, while the service's own ``JobLauncher`` runs ``hitl finetune`` (a separate process at the
configured niceness, as the nightly schedule starts it), and after. The job fine-tunes the bundled
lift policy on a few expert episodes of an unseen object (``--source full-episodes``): the same
training, recalibration and evaluation work as on takeover segments.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

from bench.harness import LocalService, Window, fresh_database, measure, reference_rate, seconds_bar, wait_stepping


def bench_finetune_load(
    robots: int = 8,
    task: str = "lift-cube",
    control_hz: float = 10.0,
    idle_seconds: float = 20.0,
    seconds: float = 60.0,
    niceness: int = 19,
    idle_priority: bool = True,
    demo_task: str = "lift-hammer",
    demo_episodes: int = 3,
    eval_episodes: int = 12,
    progress: bool = True,
) -> dict:
    from server.db import make_engine, session_factory
    from server.settings import FinetuneSettings, RobotGroup, Settings
    from sim.demos import record_demos

    with tempfile.TemporaryDirectory(prefix="hitl-bench-finetune-") as tmp:
        demos = Path(tmp) / "demos"
        record_demos(demo_task, demo_episodes, demos, seed=90_000, progress=progress)
        settings = Settings(
            data_dir=Path(tmp) / "var",
            control_hz=control_hz,
            robots=[RobotGroup(task=task, count=robots)],
            controller={"assistance": False},
            console=False,
            finetune=FinetuneSettings(schedule=None, niceness=niceness, idle_priority=idle_priority, promote=False),
        )
        fresh_database(settings)[1].dispose()
        bar = seconds_bar(2 * idle_seconds + seconds, "bench finetune-load", progress)
        try:
            with LocalService(settings, Path(tmp) / "server.log") as svc:
                fleet, launcher = svc.app.state.fleet, svc.app.state.launcher
                wait_stepping(fleet)
                time.sleep(3.0)
                idle = measure(Window(fleet), idle_seconds, bar)
                lineage = fleet.robots[0].slot.lineage
                proc = launcher.launch(
                    "bench",
                    lineage,
                    extra=[
                        "--source",
                        "full-episodes",
                        "--episodes",
                        str(demos),
                        "--eval-episodes",
                        str(eval_episodes),
                        "--eval-tasks",
                        demo_task,
                    ],
                )
                started = time.monotonic()
                ended: list[float] = []
                threading.Thread(target=lambda: (proc.wait(), ended.append(time.monotonic())), daemon=True).start()
                loaded = measure(Window(fleet, proc.pid), seconds, bar)
                job_running_whole_window = not ended
                launcher.stop()  # a job still running is interrupted (it would resume at the next run)
                job_seconds = (ended[0] if ended else time.monotonic()) - started
                idle_after = measure(Window(fleet), idle_seconds, bar)
                from server.db import FinetuneJob

                engine = make_engine(settings.db_url)
                with session_factory(engine)() as s:
                    job = s.query(FinetuneJob).order_by(FinetuneJob.id.desc()).first()
                    job_doc = {"status": job.status, "stage": job.stage, "progress": job.progress} if job else None
                engine.dispose()
        finally:
            bar.close()
    reference = reference_rate(idle, idle_after)
    return {
        "benchmark": "finetune-load",
        "config": {
            "robots": robots,
            "task": task,
            "control_hz": control_hz,
            "job_niceness": niceness,
            "job_sched_idle": idle_priority,
            "job": f"hitl finetune --source full-episodes ({demo_episodes} {demo_task} demos), "
            f"{eval_episodes} evaluation episodes per task",
        },
        "idle": idle,
        "during_job": loaded,
        "idle_after": idle_after,
        "reference_env_steps_per_s": reference,
        "cost_share": 1.0 - loaded["env_steps_per_s"] / reference,
        # the job's own run time: when shorter than the window, part of the window had no job beside it
        "job": {**(job_doc or {}), "running_whole_window": job_running_whole_window, "seconds": job_seconds},
    }

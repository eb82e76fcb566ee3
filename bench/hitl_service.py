"""``hitl bench hitl-service``: one task of the HitL benchmark through the real HTTP path, against the
same episodes in process.

A real ``hitl serve`` process runs ``episodes`` robots of ``task`` (robot r's first episode has seed
``seed + 1000 r + 1``, the fleet's rule), asking with ``signal`` under the paper's protocol (budgeted
4-step takeovers, no cooldown). ``hitl operator-bot`` (``OperatorBot``, the REST API only) answers
every request. The same seeds then run in process through ``lab.assisted.run_assisted`` with the
same controller settings, and the per-episode numbers are compared.

Two settings make the service's numbers independent of timing, so that they can be equal, not
merely close:

- ``freeze_idle``: a robot waiting for the bot, or under teleop between two of its commands, is not
  stepped (in process, the simulated operator answers at once and commands every step);
- ``batch_invariant``: the policy and the signal run robot by robot, since which robots share a tick
  differs between the two runs and batched float sums differ in the last bit.
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

from sqlalchemy import select

from bench.loop import launch_service, stop_service, wait_ready
from client.operator_bot import OperatorBot
from server.db import FINISHED, EpisodeRecord
from server.settings import Settings

KEYS = ("success", "assisted_steps", "events")


def fleet_seeds(seed: int, robots: int) -> list[int]:
    """The first episode's seed of each robot (``Fleet``: robot r starts at seed + 1000 r, + 1 per episode)."""
    return [seed + 1000 * r + 1 for r in range(robots)]


def _config(path: Path, task: str, policy: Path, robots: int, signal: str, budget: int, data_dir: Path) -> None:
    path.write_text(
        f'data_dir = "{data_dir}"\ncontrol_hz = 50\nseed = 0\n'
        '[workers]\nkind = "in-process"\nfreeze_idle = true\n[inference]\ntrace_policies = false\n'
        f'[controller]\nsignal = "{signal}"\nhand_back = "budgeted"\nbudget = {budget}\ncooldown = 0\n'
        "batch_invariant = true\n[queue]\nlease_seconds = 60\n"
        f'[[robots]]\ntask = "{task}"\ncount = {robots}\npolicy = "{Path(policy).resolve()}"\n'
    )


def run_service(
    task: str,
    policy: Path,
    episodes: int,
    signal: str,
    budget: int = 4,
    timeout: float = 1800.0,
    progress: bool = True,
) -> dict[int, dict]:
    """The first episode of each of ``episodes`` robots, served with the bot answering: seed -> numbers."""
    data_dir = Path(tempfile.mkdtemp(prefix="hitl-bench-service-"))
    config = data_dir / "fleet.toml"
    _config(config, task, policy, episodes, signal, budget, data_dir / "var")
    settings = Settings.load(config)
    seeds = set(fleet_seeds(settings.seed, episodes))
    proc, url, sessions, token = launch_service(config, settings)
    bot = OperatorBot(url, token)
    stop = threading.Event()
    thread = threading.Thread(target=bot.run, kwargs={"stop": stop.is_set, "idle_sleep": 0.02}, daemon=True)
    done: dict[int, dict] = {}
    try:
        wait_ready(url, proc, timeout=300)
        thread.start()
        deadline = time.monotonic() + timeout
        last = -1
        while len(done) < len(seeds):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the service finished {len(done)} of {len(seeds)} episodes in {timeout:.0f} s")
            if proc.poll() is not None:
                raise RuntimeError(f"hitl serve exited with code {proc.returncode}")
            time.sleep(0.5)
            with sessions() as s:
                rows = s.scalars(select(EpisodeRecord).where(EpisodeRecord.seed.in_(seeds))).all()
            done = {
                r.seed: {
                    "success": r.outcome == "success",
                    "assisted_steps": r.assisted_steps,
                    "events": r.assistance_events,
                }
                for r in rows
                if r.outcome in FINISHED
            }
            if progress and len(done) != last:
                print(f"hitl bench hitl-service: {len(done)}/{len(seeds)} episodes finished", file=sys.stderr)
                last = len(done)
    finally:
        stop.set()
        if thread.is_alive():
            thread.join(timeout=30)  # the bot stops before the service it talks to
        stop_service(proc)
        bot.close()
    return done


def run_in_process(task: str, policy_dir: Path, seeds: list[int], signal: str, budget: int = 4) -> dict[int, dict]:
    """The same episodes through ``run_assisted`` with the service's controller settings."""
    import torch

    from lab.assisted import AssistConfig, run_assisted
    from policy.checkpoint import check_fits, load_policy
    from policy.signals import load_signal

    torch.set_num_threads(1)
    policy, info = load_policy(policy_dir)
    check_fits(info, task, policy_dir)
    driver = load_signal(policy, policy_dir, signal)
    cfg = AssistConfig(hand_back="budgeted", budget=budget, n_envs=len(seeds), seed=0, batch_invariant=True)
    episodes, _ = run_assisted(policy, task, seeds, driver, None, cfg, progress=False)
    return {e.seed: {"success": e.success, "assisted_steps": e.assisted_steps, "events": e.events} for e in episodes}


def _summary(rows: dict[int, dict]) -> dict:
    n = len(rows) or 1
    return {
        "episodes": len(rows),
        "success_rate": sum(r["success"] for r in rows.values()) / n,
        "assisted_steps_per_episode": sum(r["assisted_steps"] for r in rows.values()) / n,
        "events_per_episode": sum(r["events"] for r in rows.values()) / n,
    }


def bench_hitl_service(
    task: str, policy_dir: Path, episodes: int, signal: str, budget: int = 4, progress: bool = True
) -> dict:
    seeds = fleet_seeds(0, episodes)
    served = run_service(task, policy_dir, episodes, signal, budget, progress=progress)
    local = run_in_process(task, policy_dir, seeds, signal, budget)
    per_seed = [{"seed": s, "service": served.get(s), "in_process": local.get(s)} for s in seeds]
    return {
        "task": task,
        "policy": str(policy_dir),
        "signal": signal,
        "budget": budget,
        "seeds": seeds,
        "service": _summary(served),
        "in_process": _summary(local),
        "identical": all(p["service"] == p["in_process"] for p in per_seed),
        "per_seed": per_seed,
    }

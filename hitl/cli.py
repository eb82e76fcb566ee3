"""``hitl``: the project's command line. Each subcommand's code lives in the module named beside it.

Data and policies (this module, ``policy_commands``, ``signal_commands``; shared flags in ``args``):
  tasks         list the registered tasks with their observation and action specs
  demos         record scripted demonstrations as MCAP episodes
  inspect       check episode files (and salvage truncated ones with --recover)
  experts       measure scripted-expert success and write the table to docs/ (``lab.experts``)
  train         train a diffusion policy on demonstrations
  rollout       run a policy autonomously and report success and uncertainty
  calibrate     set the uncertainty threshold from held-out validation episodes
  train-signal  train an assistance signal's models (if any) and calibrate it
  assist        assisted rollouts: a driver signal asks the simulated operator, the others in shadow
                (``lab.assisted``)
The service (``server_commands``, ``registry_commands``):
  serve         run the fleet service with the operator console at /console/
  operator-bot  the simulated operator, claiming queued robots through the API
  token         create or revoke API tokens
  policy        the policy registry: list, promote, rollback (to the version before)
  finetune      fine-tune on takeover segments, recalibrate, evaluate, gate
Data exchange (``data_commands``):
  export        lerobot: episodes and takeovers (with their labels) as a LeRobotDataset v3.0
  import        lerobot: a LeRobotDataset with our state and action layout as demonstrations
Benchmarks, reports and figures (``report_commands``, ``bench_commands``, ``console_commands``; the
code is in ``bench/``):
  bench         uncertainty, signals, fleet, api, segments, loop, operators, nights, finetune-load, hitl,
                hitl-service, floor, finetune, console, cameras: each prints its measurements as JSON
  report        sanity (the paper's sanity checks), separation (every signal's AUROC), novelty (how far
                states lie outside a policy's training range), resume (whether a policy finishes after
                a few operator steps), pregrasp (whether the lift policy closes and lifts once the
                gripper is placed at the grasp)
  plot          uncertainty: figures of U along rollouts
  docs          screenshots: the console's pictures, in headless Chromium
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path


def _cmd_tasks(args: argparse.Namespace) -> int:
    from policy.uncertainty import UncertaintyConfig
    from sim.registry import TASKS, make_task
    from sim.spaces import ACTION_LABELS

    radius = UncertaintyConfig().radius

    rows = []
    for name in TASKS:
        task = make_task(name)  # cheap: the simulator is built on first reset
        rows.append(
            {
                "task": name,
                "problem": task.problem,
                "description": task.description,
                "horizon": task.horizon,
                "observation": {"dim": task.obs_spec.dim, "parts": dict(task.obs_spec.parts)},
                "action": {
                    "dim": task.action_space.dim,
                    "labels": list(ACTION_LABELS),
                    "workspace_low": list(task.action_space.pos_low),
                    "workspace_high": list(task.action_space.pos_high),
                },
                "probe_radius": task.action_space.radius_in_units(radius),
            }
        )
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        parts = ", ".join(f"{k}({v})" for k, v in r["observation"]["parts"].items())
        print(f"{r['task']:<12} {r['problem']:<22} horizon {r['horizon']:<4} {r['description']}")
        print(f"{'':12} obs[{r['observation']['dim']}]: {parts}")
        print(
            f"{'':12} action[{r['action']['dim']}]: pos(3) rot6d(6) gripper(1), workspace "
            f"{r['action']['workspace_low']} .. {r['action']['workspace_high']}"
        )
        pr = r["probe_radius"]
        cm = " / ".join(f"{v:g}" for v in pr["position_cm"])
        print(
            f"{'':12} probe radius r={pr['r']:g}: {cm} cm (x / y / z), rot6d {pr['rot6d']:g}, gripper {pr['gripper']:g}"
        )
    return 0


def _cmd_demos(args: argparse.Namespace) -> int:
    from sim.demos import DemoRecipe, ensure_demos, record_demos
    from sim.rollout import ExecutionNoise

    noise = ExecutionNoise(args.pos_noise, args.rot_noise) if args.pos_noise or args.rot_noise else None
    if args.workers > 1:  # the recipe's missing seeds in that many processes (sim.demos.ensure_demos)
        recipe = DemoRecipe(args.task, args.episodes, args.seed, args.pos_noise, args.rot_noise, args.images)
        paths = ensure_demos(recipe, args.out, progress=not args.quiet, workers=args.workers)
        print(f"wrote {len(paths)} missing episodes of {recipe.command(str(args.out))}")
        return 0
    paths, ok = record_demos(
        args.task, args.episodes, args.out, seed=args.seed, progress=not args.quiet, noise=noise, images=args.images
    )
    print(f"wrote {len(paths)} episodes ({ok} successful) to {Path(args.out).resolve()}")
    return 0


def _cmd_inspect(args: argparse.Namespace) -> int:
    from storage.episodes import EpisodeReadError, read_episode

    files: list[Path] = []
    for p in map(Path, args.paths):
        files += sorted(p.glob("*.mcap")) if p.is_dir() else [p]
    bad = 0
    for f in files:
        try:
            ep = read_episode(f, recover=args.recover)
        except EpisodeReadError as exc:
            bad += 1
            print(json.dumps({"file": str(f), "ok": False, "error": exc.reason}))
            continue
        print(
            json.dumps(
                {
                    "file": str(f),
                    "ok": True,
                    "recovered": ep.recovered,
                    "task": ep.meta.get("task"),
                    "seed": ep.meta.get("seed"),
                    "steps": len(ep),
                    "outcome": ep.outcome,
                }
            )
        )
    return 1 if bad else 0


def _cmd_experts(args: argparse.Namespace) -> int:
    from lab.experts import expert_table, score_experts
    from sim.registry import TASKS

    tasks = args.task or list(TASKS)
    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise SystemExit(f"unknown task(s): {unknown}; registered: {list(TASKS)}")
    scores = score_experts(tasks, args.episodes, seed=args.seed, workers=args.workers)
    command = f"hitl experts --episodes {args.episodes} --seed {args.seed}"
    table = expert_table(scores, command)
    print(table)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(table)
    return 0 if all(s.rate >= 0.95 for s in scores) else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hitl", description="Human-in-the-loop robot fleet tools")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("tasks", help="list registered tasks with observation and action specs")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_cmd_tasks)

    p = sub.add_parser("demos", help="record scripted demonstrations (one MCAP file per episode)")
    p.add_argument("--task", required=True)
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--seed", type=int, default=0, help="first episode seed; episode i uses seed + i")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--pos-noise", type=float, default=0.0, help="DART: std of executed target position noise (m)")
    p.add_argument("--rot-noise", type=float, default=0.0, help="DART: std of executed target yaw noise (rad)")
    p.add_argument(
        "--images",
        action="store_true",
        help="as a policy that sees cameras: record the task's cameras' frames, the robot's own state as observation",
    )
    p.add_argument("--workers", type=int, default=1, help="record in this many processes (the missing seeds only)")
    p.set_defaults(func=_cmd_demos)

    p = sub.add_parser("inspect", help="check episode files; --recover salvages truncated ones")
    p.add_argument("paths", nargs="+", help="episode files or folders")
    p.add_argument("--recover", action="store_true")
    p.set_defaults(func=_cmd_inspect)

    p = sub.add_parser("experts", help="measure scripted expert success (writes a markdown table)")
    p.add_argument("--task", action="append", help="task id (repeatable); default: all")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, help="write the markdown table here (e.g. docs/experts.md)")
    p.set_defaults(func=_cmd_experts)

    from hitl import (
        bench_commands,
        console_commands,
        data_commands,
        policy_commands,
        registry_commands,
        report_commands,
        server_commands,
        signal_commands,
    )

    policy_commands.register(sub)
    bench = report_commands.register(sub)
    signal_commands.register(sub, bench)
    server_commands.register(sub, bench)
    bench_commands.register(bench)
    bench_commands.register_finetune(bench)
    console_commands.register(sub, bench)
    registry_commands.register(sub)
    data_commands.register(sub)
    return parser


# the benchmarks' and experiments' commands: they may name the lab's signals (``lab.signals``: ``spread-stall``);
# the service's commands never can
LAB_COMMANDS = frozenset({"bench", "report", "plot", "assist", "train-signal"})


def _signals_for(command: str) -> contextlib.AbstractContextManager:
    if command not in LAB_COMMANDS:
        return contextlib.nullcontext()
    from lab.signals import registered

    return registered()


def main(argv: list[str] | None = None) -> int:
    from storage.dataset import DatasetError

    args = build_parser().parse_args(argv)
    try:
        with _signals_for(args.command):
            return args.func(args)
    except (KeyError, ValueError, FileNotFoundError, DatasetError) as exc:
        print(f"hitl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""``hitl plot``, ``hitl report`` and ``hitl bench uncertainty``: figures, the sanity and separation
reports, and the serving cost of one robot-step (their code is in ``bench/``)."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from hitl.args import add_uncertainty_args, non_negative_int, policy_with, positive_int, set_threads, uncertainty_config
from policy.hand_back import RESUME


def _cmd_plot(args: argparse.Namespace) -> int:
    import numpy as np

    from bench.figures import plot_field, plot_timeline
    from bench.provenance import stamped
    from lab.fields import context_for, rollout_fields

    policy, info, calibration = policy_with(args)
    threshold = calibration["threshold"] if calibration else None
    seeds = list(range(args.seed, args.seed + args.episodes))
    episodes, _ = rollout_fields(
        policy, args.task, seeds, uncertainty_config(args), n_envs=min(4, len(seeds)), progress=not args.quiet
    )
    out = Path(args.out)
    first = episodes[0]
    title = f"policy {info.get('task')} on {args.task}, seed {first.seed}"
    timeline = plot_timeline(first, threshold, out / f"{args.task}-uncertainty.png", title)
    peak = int(np.argmax(first.uncertainty))
    field = plot_field(first.fields[peak], out / f"{args.task}-field.png", f"{title}, step {peak}")
    label, _ = context_for(args.task)
    report = {
        "task": args.task,
        "policy": str(args.policy),
        "threshold": threshold,
        "figures": [str(timeline), str(field)],
        "context": label,
        "episodes": [],
    }
    for ep in episodes:
        u = np.asarray(ep.uncertainty)
        ctx = np.asarray(ep.context)
        above = u >= threshold if threshold is not None else np.zeros_like(u, dtype=bool)
        report["episodes"].append(
            {
                **ep.summary(),
                "peak_step": int(u.argmax()),
                "modes_at_peak": ep.fields[int(u.argmax())].n,
                "context_at_peak": float(ctx[u.argmax()]),
                "first_above_step": int(np.argmax(above)) if above.any() else None,
                "context_at_first_above": float(ctx[np.argmax(above)]) if above.any() else None,
                "steps_above": int(above.sum()),
                "median_context_above": float(np.median(ctx[above])) if above.any() else None,
                "median_context": float(np.median(ctx)),
            }
        )
    text = json.dumps(stamped(report), indent=2)
    path = args.report or out / f"{args.task}-uncertainty.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n")
    print(text if args.json else f"wrote {timeline} and {field}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import numpy as np

    from bench.provenance import stamped
    from bench.uncertainty import bench_uncertainty
    from lab.fields import rollout_fields
    from policy.devices import prepare_for_serving
    from policy.signals import SignalError, load_signal

    set_threads(args)
    policy, info, _ = policy_with(args)
    prepare_for_serving(policy, args.device)  # ValueError (exit 2) when this machine lacks the device
    asking, asking_skipped = None, None
    try:
        asking = load_signal(policy, args.policy, args.asking or "spread") if args.asking != "" else None
    except SignalError as exc:
        if args.asking:  # asked for by name: an error
            raise ValueError(str(exc)) from exc
        asking_skipped = f"spread not timed: {exc}"  # the default, where this policy has it
    task = args.task or info["task"]
    seeds = list(range(args.seed, args.seed + args.episodes))
    episodes, _ = rollout_fields(
        policy, task, seeds, uncertainty_config(args), n_envs=min(4, len(seeds)), progress=not args.quiet
    )
    inputs = [x for ep in episodes for x in ep.probe_inputs]
    order = np.random.default_rng(0).permutation(len(inputs))
    obs = np.stack([inputs[i][0] for i in order])
    centers = np.stack([inputs[i][1] for i in order])
    result = bench_uncertainty(  # ValueError (exit 2): a fleet size the rollouts gave too few states for
        policy,
        obs,
        centers,
        tuple(args.fleet_sizes),
        args.repeats,
        uncertainty_config(args),
        asking=asking,
        progress=not args.quiet,
    )
    result = {
        "benchmark": "uncertainty",
        "policy": str(args.policy),
        **({"asking_skipped": asking_skipped} if asking_skipped else {}),
        "states_from": f"{task} rollouts, seeds {seeds[0]}..{seeds[-1]}",
        **result,
    }
    print(json.dumps(stamped(result), indent=2 if not args.json else None))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    set_threads(args)
    from bench.provenance import stamped
    from bench.sanity import sanity_report

    episodes = {
        "lift-cube": args.episodes_lift,
        "lift-other": args.episodes_other,
        "cup-stack": args.episodes_cup,
        "open-drawer": args.episodes_drawer,
    }
    command = "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    text, results = sanity_report(args.lift, args.cup, args.drawer, episodes, args.seed, not args.quiet, command)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
        Path(args.out).with_suffix(".json").write_text(json.dumps(stamped(results), indent=2) + "\n")
    print(text)
    return 0


def _write_report(report, out: Path | None) -> int:
    """Writes ``report`` (a ``to_dict``/``markdown`` report) as JSON to ``out``, with the command that
    made it, and prints its table."""
    from bench.provenance import stamped

    doc = stamped({"command": "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:]), **report.to_dict()})
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(doc, indent=2) + "\n")
    print(report.markdown())
    return 0


def _cmd_separation(args: argparse.Namespace) -> int:
    set_threads(args)
    from bench.separation import shift_separation
    from policy.checkpoint import check_fits, load_policy

    policy, info = load_policy(args.policy)
    in_task = args.in_task or info.get("task")
    if not in_task:
        raise ValueError(f"{args.policy}/config.json names no task: pass --in-task")
    for task in dict.fromkeys([in_task, *args.shift_tasks]):
        check_fits(info, task, args.policy)
    report = shift_separation(
        policy,
        args.policy,
        in_task,
        args.shift_tasks,
        args.episodes,
        args.seed,
        args.signals,
        progress=not args.quiet,
    )
    return _write_report(report, args.out)


def _cmd_novelty(args: argparse.Namespace) -> int:
    set_threads(args)
    from bench.novelty import task_novelty
    from policy.checkpoint import check_fits, load_policy
    from policy.signals.choice_stall import ChoiceStallConfig

    policy, info = load_policy(args.policy)
    for task in dict.fromkeys(args.tasks):
        check_fits(info, task, args.policy)
    gate = args.gate if args.gate is not None else ChoiceStallConfig().novelty_gate
    report = task_novelty(policy, args.policy, args.tasks, args.episodes, args.seed, gate, progress=not args.quiet)
    return _write_report(report, args.out)


def _cmd_resume(args: argparse.Namespace) -> int:
    set_threads(args)
    from bench.resume import ResumeReport, task_resume
    from policy.checkpoint import check_fits, load_policy

    policy, info = load_policy(args.policy)
    task = args.task or info.get("task")
    if not task:
        raise SystemExit("hitl report resume: the policy names no task; give --task")
    check_fits(info, task, args.policy)
    row = task_resume(
        policy,
        str(args.policy),
        task,
        args.at,
        args.budgets,
        args.episodes,
        args.seed,
        progress=not args.quiet,
        resume=args.resume,
    )
    return _write_report(ResumeReport([row]), args.out)


def _cmd_pregrasp(args: argparse.Namespace) -> int:
    set_threads(args)
    from bench.resume import PregraspReport, task_pregrasp
    from policy.checkpoint import check_fits, load_policy

    policy, info = load_policy(args.policy)
    tasks = args.tasks or [info.get("task")]
    if not all(tasks):
        raise SystemExit("hitl report pregrasp: the policy names no task; give --tasks")
    for task in dict.fromkeys(tasks):
        check_fits(info, task, args.policy)
    rows = [
        task_pregrasp(policy, str(args.policy), task, args.episodes, args.seed, progress=not args.quiet)
        for task in dict.fromkeys(tasks)
    ]
    return _write_report(PregraspReport(rows), args.out)


def register(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """Adds ``plot``, ``report`` and ``bench`` (with ``bench uncertainty``); returns ``bench``'s subparsers."""
    p = sub.add_parser("plot", help="write figures to docs/figures/")
    what = p.add_subparsers(dest="figure", required=True)
    q = what.add_parser("uncertainty", help="U timeline against the threshold and the vector field at its peak")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--task", required=True)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--episodes", type=int, default=1, help="more episodes only add to the JSON report")
    q.add_argument("--ddim-steps", type=int, default=None)
    q.add_argument("--out", type=Path, default=Path("docs/figures"), help="the figures' folder")
    q.add_argument("--json", action="store_true", help="print the per-episode report (peaks, steps above) as JSON")
    q.add_argument(
        "--report",
        type=Path,
        default=None,
        help="where to write that report (default: OUT/TASK-uncertainty.json, beside the figures)",
    )
    q.add_argument("--quiet", action="store_true")
    add_uncertainty_args(q)
    q.set_defaults(func=_cmd_plot)

    p = sub.add_parser("report", help="run the paper's sanity checks and write them to docs/results/")
    what = p.add_subparsers(dest="report", required=True)
    q = what.add_parser("sanity", help="lift on seen/unseen objects, cup-stack grasp vs insertion, drawer choice")
    q.add_argument("--lift", type=Path, help="lift-cube policy folder")
    q.add_argument("--cup", type=Path, help="cup-stack policy folder")
    q.add_argument("--drawer", type=Path, help="open-drawer policy folder")
    q.add_argument("--episodes-lift", type=positive_int, default=50)
    q.add_argument("--episodes-other", type=positive_int, default=50, help="per unseen lift object")
    q.add_argument("--episodes-cup", type=positive_int, default=50)
    q.add_argument("--episodes-drawer", type=positive_int, default=50)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--out", type=Path, help="markdown file (a .json with the numbers is written beside it)")
    q.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_report)
    q = what.add_parser("separation", help="AUROC of every signal for shifted vs training-distribution states")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--in-task", default=None, help="training-distribution task (default: the policy's)")
    q.add_argument("--shift-tasks", nargs="+", default=["lift-nut", "lift-hammer", "lift-hook"])
    q.add_argument("--episodes", type=positive_int, default=8, help="rollouts per task")
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--signals", nargs="+", default=None, help="default: every registered signal")
    q.add_argument("--out", type=Path, help="JSON file to write (the markdown table is printed)")
    q.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_separation)
    q = what.add_parser("novelty", help="how far each task's states lie outside the policy's training range")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--tasks", nargs="+", required=True)
    q.add_argument("--episodes", type=positive_int, default=8, help="rollouts per task")
    q.add_argument("--seed", type=int, default=2000, help="first seed (default: the development seeds)")
    q.add_argument("--gate", type=float, default=None, help="default: choice-stall's novelty_gate")
    q.add_argument("--out", type=Path, help="JSON file to write (the markdown table is printed)")
    q.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_novelty)
    q = what.add_parser("resume", help="one takeover of a few operator steps at each step k: does the policy finish?")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--task", default=None, help="default: the policy's task")
    q.add_argument("--at", type=non_negative_int, nargs="+", required=True, help="policy steps of the takeover")
    q.add_argument("--budgets", type=positive_int, nargs="+", default=[4], help="operator steps (default: 4)")
    q.add_argument("--episodes", type=positive_int, default=8, help="episodes per takeover step")
    q.add_argument("--seed", type=int, default=2000, help="first seed (default: the development seeds)")
    q.add_argument(
        "--resume",
        choices=RESUME,
        default="restart",
        help="after the hand-back the policy's history restarts (default) or keeps the takeover's frames",
    )
    q.add_argument("--out", type=Path, help="JSON file to write (the markdown table is printed)")
    q.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_resume)
    q = what.add_parser(
        "pregrasp",
        help="the operator places the open gripper at the grasp and hands back: does the policy close and lift?",
    )
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--tasks", nargs="+", default=None, help="default: the policy's task")
    q.add_argument("--episodes", type=positive_int, default=12, help="episodes per task")
    q.add_argument("--seed", type=int, default=2000, help="first seed (default: the development seeds)")
    q.add_argument("--out", type=Path, help="JSON file to write (the markdown table is printed)")
    q.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_pregrasp)

    p = sub.add_parser("bench", help="speed measurements, printed as JSON")
    what = p.add_subparsers(dest="target", required=True)
    q = what.add_parser("uncertainty", help="uncertainty metric vs DDIM sampling; torch vs sklearn GMM")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--task", default=None, help="task to collect rollout states on (default: the policy's)")
    q.add_argument("--episodes", type=int, default=4)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--fleet-sizes", type=positive_int, nargs="+", default=[1, 8, 16, 32])
    q.add_argument("--repeats", type=positive_int, default=5)
    q.add_argument("--device", default="cpu", help="where the policy and the uncertainty run: cpu, cuda, cuda:N")
    q.add_argument(
        "--asking",
        default=None,
        help="the fleet's asking signal to time as well (default: spread, when the policy has it; '' for none)",
    )
    q.add_argument("--ddim-steps", type=int, default=None)
    q.add_argument("--threads", type=int, default=None)
    q.add_argument("--json", action="store_true", help="one line of JSON")
    q.add_argument("--quiet", action="store_true")
    add_uncertainty_args(q)
    q.set_defaults(func=_cmd_bench)

    q = what.add_parser("cameras", help="the policy's cameras: render cost per step, MuJoCo's defaults vs as served")
    q.add_argument(
        "--tasks", nargs="+", default=None, help="tasks (default: lift-cube, lift-hammer, cup-stack, open-drawer)"
    )
    q.add_argument("--steps", type=positive_int, default=60, help="control steps of an expert episode per task")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--figure", type=Path, default=None, help="PNG of what the policy sees")
    q.add_argument("--out", type=Path, default=None, help="JSON file to write (also printed)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_cameras)
    return what


def _cmd_bench_cameras(args: argparse.Namespace) -> int:
    import json

    from bench.cameras import TASKS, CameraBench, bench_cameras, plot_policy_views
    from bench.provenance import stamped

    plan = CameraBench(tuple(args.tasks or TASKS), args.seed, args.steps)
    result, views = bench_cameras(plan, progress=not args.quiet)
    if args.figure is not None:
        result["figure"] = str(plot_policy_views(views, args.figure))
    text = json.dumps(stamped(result), indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text)
    return 0

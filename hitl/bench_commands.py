"""``hitl bench hitl``: the human-in-the-loop benchmark (``bench.hitl.run``), printed as JSON."""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shlex
import sys
from pathlib import Path

LIFT_SHIFTS = ("lift-nut", "lift-hammer", "lift-hook")
TASKS = (*LIFT_SHIFTS, "cup-stack", "open-drawer")
POLICY_OF = {"lift-cube": "lift-cube", **{t: "lift-cube" for t in LIFT_SHIFTS}, "cup-stack": "cup-stack"}
POLICY_OF["open-drawer"] = "open-drawer"


def _policies(args: argparse.Namespace, tasks: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    given = {}
    for pair in args.policy or []:
        task, sep, folder = pair.partition("=")
        if not sep:
            raise ValueError(f"--policy expects task=folder, got {pair!r}")
        given[task] = folder
    out = {}
    for t in tasks:
        if t in given:
            out[t] = given[t]
        elif t in POLICY_OF:
            out[t] = str(Path(args.policy_root) / POLICY_OF[t])
        else:
            raise ValueError(f"no policy for task {t!r}: pass --policy {t}=FOLDER")
    for t, folder in out.items():
        if not (Path(folder) / "config.json").is_file():
            raise ValueError(f"{folder}: no policy there (for task {t}); train one or pass --policy {t}=FOLDER")
    return tuple(sorted(out.items()))


def recipe_from_args(args: argparse.Namespace):
    from bench.hitl.run import DEFAULT_QUANTILES, QUICK_QUANTILES, Recipe, SignalSpec
    from policy.signals import SIGNALS

    quick = args.quick
    tasks = tuple(args.tasks or (("lift-hammer",) if quick else TASKS))
    false_alarm = None if args.false_alarm_task in ("", "none") else args.false_alarm_task
    signals = args.signals or list(SIGNALS)
    specs = tuple(SignalSpec.parse(s) for s in signals)
    for s in specs:
        if s.name not in SIGNALS:
            raise KeyError(f"unknown signal {s.name!r}; registered signals: {', '.join(SIGNALS)}")
    quantiles = tuple(args.quantiles or (QUICK_QUANTILES if quick else DEFAULT_QUANTILES))
    episodes = args.episodes if args.episodes is not None else (4 if quick else 20)
    all_tasks = tasks + ((false_alarm,) if false_alarm and false_alarm not in tasks else ())
    return Recipe(
        policies=_policies(args, all_tasks),
        tasks=tasks,
        signals=specs,
        quantiles=quantiles,
        false_alarm_task=false_alarm,
        episodes=episodes,
        seed=args.seed,
        reference_episodes=args.reference_episodes if args.reference_episodes is not None else (4 if quick else 10),
        reference_seed=args.reference_seed,
        budget=args.budget,
        envs=args.envs if args.envs is not None else max(episodes, 1),
        sweep=not args.no_sweep,
        shadow=not args.no_shadow,
        exhaustive=args.exhaustive,
    )


def _cmd_bench_hitl(args: argparse.Namespace) -> int:
    from bench.hitl.report import summarize
    from bench.hitl.run import default_jobs, run_benchmark

    recipe = recipe_from_args(args)
    if args.default_signal is not None and args.default_signal not in {s.label for s in recipe.signals}:
        raise ValueError(f"--default-signal {args.default_signal!r} is not among --signals")
    floor = None
    if args.floor is not None:
        try:
            floor = json.loads(args.floor.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"--floor {args.floor}: not a readable floor summary ({exc})") from None
        if not isinstance(floor, dict) or not isinstance(floor.get("tasks"), dict):
            raise ValueError(f"--floor {args.floor}: not a floor summary (hitl bench floor --json): no tasks")
    raw = run_benchmark(
        recipe, args.cache, jobs=args.jobs or default_jobs(), progress=not args.quiet, cached_only=args.cached_only
    )
    if raw.get("pending_references"):
        raise ValueError(f"--cached-only: the reference rollouts of {raw['pending_references']} have not run yet")
    summary = summarize(raw, floor)
    summary["provenance"] = {
        **_provenance(),
        "seeds": [recipe.seed, recipe.seed + recipe.episodes - 1],
        "reference_seeds": [recipe.reference_seed, recipe.reference_seed + recipe.reference_episodes - 1],
    }
    if args.raw:
        args.raw.parent.mkdir(parents=True, exist_ok=True)
        args.raw.write_text(json.dumps(raw))
    if args.report:
        from bench.hitl.docs import write_report

        summary["report"] = str(write_report(summary, raw, args.report, args.figures, args.section))
        if floor is not None and args.default_signal:
            from bench.hitl.headline import markdown as headline
            from bench.report_sections import replace_section

            replace_section(args.report, "headline", headline(summary, floor, args.default_signal))
    print(json.dumps(summary, indent=None if args.json else 2))
    return 0


def _cmd_bench_hitl_service(args: argparse.Namespace) -> int:
    from bench.hitl_service import bench_hitl_service
    from bench.provenance import stamped
    from sim.registry import TASKS

    if args.task not in TASKS:
        raise ValueError(f"unknown task {args.task!r}; tasks: {', '.join(TASKS)}")
    if not (args.policy / "config.json").is_file():
        raise ValueError(f"{args.policy}: no policy there (config.json not found)")
    if args.episodes < 1 or args.budget < 1:
        raise ValueError("--episodes and --budget must be >= 1")
    from policy.checkpoint import check_fits, load_policy
    from policy.signals import load_signal
    from policy.signals.registry import signal_class

    signal_class(args.signal)  # an unknown name is named with the registered ones
    policy, info = load_policy(args.policy)
    check_fits(info, args.task, args.policy)  # a policy that cannot run the task, before serving
    load_signal(policy, args.policy, args.signal)  # a missing calibration, before serving

    out = bench_hitl_service(args.task, args.policy, args.episodes, args.signal, args.budget, not args.quiet)
    out["command"] = "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    print(json.dumps(stamped(out), indent=None if args.json else 2))
    return 0 if out["identical"] else 1


def _cmd_bench_floor(args: argparse.Namespace) -> int:
    from bench.floor import FloorRecipe, markdown, run_floor
    from bench.hitl.run import default_jobs

    tasks = tuple(args.tasks or TASKS)
    recipe = FloorRecipe(
        policies=_policies(args, tasks),
        tasks=tasks,
        episodes=args.episodes,
        seed=args.seed,
        dev_episodes=args.dev_episodes,
        dev_seed=args.dev_seed,
        budget=args.budget,
        finalists=args.finalists,
        operator=args.operator,
        resume=args.resume,
        quick=args.quick,
    )
    summary = run_floor(recipe, args.cache, jobs=args.jobs or default_jobs(), progress=not args.quiet)
    summary["provenance"] = _provenance()
    if args.report:
        from bench.report_sections import replace_section

        summary["report"] = str(replace_section(args.report, args.section, markdown(summary)))
    print(json.dumps(summary, indent=None if args.json else 2))
    return 0


def _provenance() -> dict:
    """The command line that made a result, its commit and date (``bench.provenance``), and the machine."""
    from bench.provenance import provenance

    return {
        **provenance(),
        "machine": f"{platform.machine()}, {_cpus()} CPU cores, {platform.python_implementation()} "
        f"{platform.python_version()}, no GPU used",
    }


def _cpus() -> int:
    import os

    return os.cpu_count() or 1


def register(bench: argparse._SubParsersAction) -> None:
    from bench.hitl.run import VERSION

    q = bench.add_parser(
        "hitl",
        help="human-assisted steps per episode to reach success, per task and assistance signal (the paper's table)",
        description=f"benchmark format {VERSION}; results are cached per cell under --cache, so reruns are incremental",
    )
    q.add_argument("--quick", action="store_true", help="lift-hammer only, 4 episodes, 3 thresholds (minutes)")
    q.add_argument("--tasks", nargs="+", default=None, help=f"default: {' '.join(TASKS)}")
    q.add_argument("--false-alarm-task", default="lift-cube", help="in-distribution task for false alarms ('none')")
    q.add_argument("--signals", nargs="+", default=None, help="registered signals, NAME:key=value for variants")
    q.add_argument(
        "--policy-root",
        default="policies",
        help="folder holding lift-cube/, cup-stack/, open-drawer/ (default: the bundled policies; "
        "signals without files there are skipped and named)",
    )
    q.add_argument("--policy", nargs="+", metavar="TASK=FOLDER", help="the policy for a task (overrides the root)")
    q.add_argument("--quantiles", nargs="+", type=float, default=None, help="threshold grid (reference quantiles)")
    q.add_argument("--episodes", type=int, default=None, help="episodes per task (default 20; --quick 4)")
    q.add_argument("--seed", type=int, default=1000, help="first evaluation seed")
    q.add_argument("--reference-episodes", type=int, default=None, help="reference rollouts per policy (default 10)")
    q.add_argument("--reference-seed", type=int, default=5000)
    q.add_argument("--budget", type=int, default=4, help="operator steps per assistance request")
    q.add_argument("--envs", type=int, default=None, help="robots stepped together (default: all episodes)")
    q.add_argument("--jobs", type=int, default=None, help="worker processes (default: up to 2)")
    q.add_argument("--cache", type=Path, default=Path("runs/bench-hitl"), help="cell results cache")
    q.add_argument("--no-sweep", action="store_true", help="only each signal's own calibration")
    q.add_argument("--cached-only", action="store_true", help="run nothing: report the cells cached so far")
    q.add_argument("--exhaustive", action="store_true", help="sweep every threshold (default: stop at 100%% success)")
    q.add_argument("--no-shadow", action="store_true", help="skip the shadow runs (false alarms, diagnostics)")
    q.add_argument("--raw", type=Path, default=None, help="also write every cell's raw result here")
    q.add_argument(
        "--floor",
        type=Path,
        default=None,
        help='the floor\'s JSON (hitl bench floor): also score the signals against its "needs help" label',
    )
    q.add_argument(
        "--default-signal",
        default=None,
        help="with --report and --floor: the fleet's asking signal, shown at its own calibration in the report's "
        "headline (the paper's table beside ours, its `headline` section)",
    )
    q.add_argument("--report", type=Path, default=None, help="write the markdown report here")
    q.add_argument("--figures", type=Path, default=Path("docs/figures"), help="figures folder for --report")
    q.add_argument("--section", default="main", help="the report section this run writes (ablations apart)")
    q.add_argument("--json", action="store_true", help="one line of JSON")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_hitl)

    q = bench.add_parser(
        "hitl-service",
        help="one task of the HitL benchmark through hitl serve and hitl operator-bot, against the same seeds "
        "in process (exit 1 when the numbers differ)",
    )
    q.add_argument("--task", default="lift-hammer")
    q.add_argument("--policy", type=Path, default=Path("runs/lift-cube"))
    q.add_argument("--signal", default="choice-stall", help="default: the fleet's")
    q.add_argument("--episodes", type=int, default=8, help="robots, one episode each")
    q.add_argument("--budget", type=int, default=4)
    q.add_argument("--json", action="store_true", help="one line of JSON")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_hitl_service)

    q = bench.add_parser(
        "floor",
        help="the fewest operator steps any asking signal could need: an oracle that asks from the simulator's "
        "state, swept on development seeds, best-of-sweep on the evaluation seeds (bench.floor)",
    )
    q.add_argument("--tasks", nargs="+", default=None, help=f"default: {' '.join(TASKS)}")
    q.add_argument("--policy-root", default="policies", help="folder holding lift-cube/, cup-stack/, open-drawer/")
    q.add_argument("--policy", nargs="+", metavar="TASK=FOLDER", help="the policy for a task (overrides the root)")
    q.add_argument("--episodes", type=int, default=20, help="evaluation episodes per task")
    q.add_argument("--seed", type=int, default=1000, help="first evaluation seed")
    q.add_argument("--dev-episodes", type=int, default=12, help="development episodes per grid point")
    q.add_argument("--dev-seed", type=int, default=2000, help="first development seed")
    q.add_argument("--budget", type=int, default=4, help="operator steps per request")
    q.add_argument("--finalists", type=int, default=3, help="grid points run on the evaluation seeds")
    q.add_argument("--operator", default="carry-on", help="the simulated operator's style: carry-on or replan")
    q.add_argument(
        "--resume",
        default="restart",
        help="after a hand-back the policy's history restarts (default) or keeps the takeover's frames ('history')",
    )
    q.add_argument("--quick", action="store_true", help="one grid point per window (its widest reach, no cap)")
    q.add_argument("--jobs", type=int, default=None, help="worker processes (default: up to 2)")
    q.add_argument("--cache", type=Path, default=Path("runs/bench-floor"), help="cell results cache")
    q.add_argument("--report", type=Path, default=None, help="write the floor table into this page")
    q.add_argument("--section", default="floor", help="the report section this run writes")
    q.add_argument("--json", action="store_true", help="one line of JSON")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_floor)


def _cmd_bench_finetune(args: argparse.Namespace) -> int:
    import torch

    from bench.finetune.report import markdown, plot, summarize
    from bench.finetune.run import FinetuneBenchConfig, run_bench
    from bench.provenance import stamped
    from bench.report_sections import replace_section
    from policy.finetune import FinetuneConfig

    given = {k: v for k, v in (("policy", args.policy), ("eval_episodes", args.episodes)) if v is not None}
    if args.sources:
        given["sources"] = tuple(args.sources)
    if args.counts:
        given["counts"] = tuple(args.counts)
    finetune = {k: getattr(args, k) for k in ("ratio", "steps", "lr") if getattr(args, k) is not None}
    if args.keep_obs_range:
        finetune["widen_obs_range"] = False
    if args.successful_only:
        finetune["successful_only"] = True
    if args.takeover_tail is not None:
        finetune["takeover_tail"] = args.takeover_tail
    if finetune:
        given["finetune"] = FinetuneConfig(**finetune)
    if args.return_after is not None:
        given["return_after"] = args.return_after
    if args.hand_back is not None:
        given["hand_back"] = args.hand_back
    if args.stride is not None:
        given["stride"] = args.stride
    if args.repeats is not None:
        given["repeats"] = args.repeats
    cfg = FinetuneBenchConfig.quick(**given) if args.quick else FinetuneBenchConfig(**given)  # validated first
    torch.set_num_threads(args.threads)
    result = run_bench(cfg, args.cache, progress=not args.quiet)
    summary = summarize(result)
    command = "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    result |= {
        "summary": {**summary, "curves": {s: {str(k): v for k, v in c.items()} for s, c in summary["curves"].items()}},
        "command": command,
        "machine": {"platform": platform.platform(), "date": datetime.date.today().isoformat()},
    }
    stamped(result)
    if args.report:
        section = args.section or ("finetune-quick" if args.quick else "finetune")
        figure = plot(summary, Path(args.figures) / f"{section}.png")
        body = markdown(result, summary, figure, Path(args.report), command, section)
        replace_section(Path(args.report), section, body)
    print(json.dumps(result, indent=None if args.json else 2))
    return 0


def register_finetune(bench: argparse._SubParsersAction) -> None:
    q = bench.add_parser(
        "finetune",
        help="unseen-object success against fine-tuning samples, per data source (the paper's fine-tuning figure)",
        description="every point starts from the same pretrained policy; results are cached per point under --cache",
    )
    q.add_argument("--quick", action="store_true", help="takeover:spread and full-trajectory, K = 50, 100, 10 episodes")
    q.add_argument(
        "--policy",
        default=None,
        help="default: policies/state/lift-cube, the state-based lift policy (runs/lift-cube has every signal)",
    )
    q.add_argument(
        "--sources",
        nargs="+",
        default=None,
        help="takeover:SIGNAL ..., full-trajectory and/or expert:grasp (the demonstrations' steps around the grasp)",
    )
    q.add_argument("--counts", nargs="+", type=int, default=None, help="sample counts K (default 20 50 100 200)")
    q.add_argument("--episodes", type=int, default=None, help="evaluation episodes per task (default 20)")
    q.add_argument("--ratio", type=float, default=None, help="takeover share of each mini-batch (default 0.5)")
    q.add_argument("--steps", type=int, default=None, help="fixed training steps (default: scales with the data)")
    q.add_argument("--lr", type=float, default=None, help="learning rate (default: the job's, 5e-4)")
    q.add_argument(
        "--keep-obs-range",
        action="store_true",
        help="fine-tune with the parent's observation range (default: widened to cover the takeover data)",
    )
    q.add_argument(
        "--return-after", type=int, default=None, help="the operator hands back after N calm steps (default 1)"
    )
    q.add_argument(
        "--hand-back",
        choices=["continuous", "budgeted", "operator"],
        default=None,
        help="how takeovers end (default continuous; operator: the operator hands back once the object is held)",
    )
    q.add_argument(
        "--stride",
        type=int,
        default=None,
        help="fine-tune on one step in N of each takeover or demonstration (default 1)",
    )
    q.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="each point N times: other seeded draws of the samples and fine-tuning seeds (default 1)",
    )
    q.add_argument(
        "--successful-only",
        action="store_true",
        help="fine-tune only on takeovers in episodes that succeeded (as hitl finetune --successful-only)",
    )
    q.add_argument(
        "--takeover-tail",
        type=int,
        default=None,
        metavar="N",
        help="fine-tune on the last N steps of each takeover (as hitl finetune --takeover-tail)",
    )
    q.add_argument("--section", default=None, help="the report section's name (default finetune / finetune-quick)")
    q.add_argument("--cache", default="runs/bench-finetune")
    q.add_argument(
        "--report", default=None, help="write the table into this markdown file (docs/benchmarks/finetune.md)"
    )
    q.add_argument("--figures", default="docs/figures", help="figures folder for --report")
    q.add_argument("--threads", type=int, default=1)
    q.add_argument("--json", action="store_true", help="compact JSON")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_finetune)

"""``hitl train-signal | assist | bench signals``: the assistance signals side of the CLI."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path


def _parse_settings(pairs: list[str]) -> dict:
    """``key=value`` pairs; values are JSON when they parse as JSON, else strings."""
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise ValueError(f"--set expects key=value, got {pair!r}")
        key, value = pair.split("=", 1)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _load(args: argparse.Namespace):
    from policy.checkpoint import load_policy

    if getattr(args, "threads", None):
        import torch

        torch.set_num_threads(args.threads)
    return load_policy(args.policy)


def _check_fits(args: argparse.Namespace, info: dict) -> str:
    """The task the policy is run on (``--task``, else its own); CheckpointError (exit 2) when it cannot
    run it (``policy.checkpoint.check_fits``)."""
    from policy.checkpoint import check_fits

    task = args.task or info["task"]
    check_fits(info, task, args.policy)
    return task


def _cmd_train_signal(args: argparse.Namespace) -> int:
    from policy.signal_data import demo_data, policy_rollouts
    from policy.signals import make_signal, save_signal
    from storage.paths import portable

    policy, info = _load(args)
    signal = make_signal(args.signal, policy, _parse_settings(args.set))
    data = demo_data(policy, info, args.data)
    if signal.needs_rollouts or signal.has_models:
        task = _check_fits(args, info)
        seeds = list(range(args.rollout_seed, args.rollout_seed + args.rollouts))
        data.rollouts = policy_rollouts(policy, args.policy, task, seeds, n_envs=args.envs, progress=not args.quiet)
    training = signal.fit(data, args.steps, progress=not args.quiet) if signal.has_models else None
    calibration = signal.calibrate(data, progress=not args.quiet)
    rollouts = data.rollouts
    folder = save_signal(
        signal,
        args.policy,
        {
            "training": training,
            "data": {
                "demonstrations": portable(args.data),
                "train_steps": len(data.train),
                "val_steps": len(data.val),
                "rollouts": None
                if rollouts is None
                else {
                    "task": args.task or info["task"],
                    "episodes": len(rollouts.names),
                    "successes": int(sum(rollouts.success[rows[0]] for rows in rollouts.episodes())),
                    "steps": len(rollouts),
                    "seeds": [args.rollout_seed, args.rollout_seed + args.rollouts - 1],
                },
            },
            "command": "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        },
    )
    print(
        json.dumps(
            {"signal": args.signal, "folder": str(folder), "calibration": calibration, "training": training}, indent=2
        )
    )
    return 0


def _signals_for(policy, policy_dir: Path, names: list[str]) -> dict:
    """The named signals as saved next to the policy (``load_signal``)."""
    from policy.signals import SignalError, load_signal

    out = {}
    for name in names:
        try:
            out[name] = load_signal(policy, policy_dir, name)
        except SignalError as exc:
            raise SignalError(f"{name}: {exc}") from exc
    return out


def _variant(policy, policy_dir: Path, text: str):
    """``NAME`` as saved next to the policy, or ``NAME:key=value`` (one setting: the list is comma-separated)
    with that setting changed and the saved calibration kept (for what it costs, not what it decides)."""
    from policy.signals import make_signal

    name, _, setting = text.partition(":")
    saved = _signals_for(policy, policy_dir, [name])[name]
    if not setting:
        return saved
    key, eq, value = setting.partition("=")
    if not eq:
        raise ValueError(f"signal {text!r}: expected NAME:key=value")
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError:
        parsed = value
    variant = make_signal(name, policy, {**saved.config.to_dict(), key.strip(): parsed})
    variant.calibration = saved.calibration
    return variant


def _names(value: str) -> list[str]:
    from policy.signals import SIGNALS

    if value == "all":
        return list(SIGNALS)
    names = [n.strip() for n in value.split(",") if n.strip()]
    for n in names:
        if n.partition(":")[0] not in SIGNALS:
            raise KeyError(f"unknown signal {n!r}; registered signals: {', '.join(SIGNALS)}")
    return names


def _cmd_assist(args: argparse.Namespace) -> int:
    from bench.provenance import stamped
    from lab.assisted import AssistConfig, run_assisted, summarize_assisted
    from policy.signals import SignalError

    policy, info = _load(args)
    _check_fits(args, info)
    names = _names(args.shadow) if args.shadow else []
    signals = _signals_for(policy, args.policy, [args.driver])
    skipped = {}
    for name in dict.fromkeys(names):
        if name in signals:
            continue
        try:
            signals.update(_signals_for(policy, args.policy, [name]))
        except SignalError as exc:
            if args.shadow != "all":
                raise
            skipped[name] = str(exc)  # 'all' means every signal this policy has
    for why in skipped.values():
        print(f"hitl assist: shadow signal skipped: {why}", file=sys.stderr)
    if args.random_rate is not None and "random" in signals:
        signals["random"].match_rate(args.random_rate, "--random-rate")
    thresholds = {name: s.threshold for name, s in signals.items()}
    driver = signals.pop(args.driver)
    seeds = list(range(args.seed, args.seed + args.episodes))
    cfg = AssistConfig(
        hand_back=args.mode,
        budget=args.budget,
        cooldown=args.cooldown,
        watchdog=args.watchdog,
        n_envs=args.envs,
        return_after=None if args.hand_back_when_held else 1,  # continuous: the operator alone, or the paper's rule
        operator_hands_back=args.hand_back_when_held,
    )
    episodes, timing = run_assisted(policy, args.task or info["task"], seeds, driver, signals, cfg, not args.quiet)
    out = {
        "task": args.task or info["task"],
        "policy": str(args.policy),
        "mode": args.mode,
        "budget": args.budget if args.mode == "budgeted" else None,
        "cooldown": args.cooldown,
        "watchdog": args.watchdog,
        "operator_hands_back_when_held": args.hand_back_when_held,
        **summarize_assisted(episodes),
        "shadow_skipped": skipped,
        "seconds": timing["seconds"],
        "per_episode": [e.summary() for e in episodes],
    }
    if args.scores:
        out["scores"] = [{"seed": e.seed, "operator": e.operator, "scores": e.scores} for e in episodes]
    if args.plot:
        from bench.figures import plot_signal_comparison

        args.plot.mkdir(parents=True, exist_ok=True)
        path = plot_signal_comparison(
            episodes[0], thresholds, args.plot / f"{out['task']}-signals.png", f"{out['task']}, seed {episodes[0].seed}"
        )
        out["figure"] = str(path)
    print(json.dumps(stamped(out), indent=None if args.json else 2))
    return 0


def _cmd_bench_signals(args: argparse.Namespace) -> int:
    import torch

    from bench.provenance import stamped
    from bench.signals import bench_signals
    from policy.checkpoint import load_policy
    from policy.signal_data import policy_rollouts
    from policy.signals import SignalError

    policy, info = _load(args)
    task = _check_fits(args, info)
    seeds = list(range(args.seed, args.seed + args.episodes))
    steps = policy_rollouts(policy, args.policy, task, seeds, n_envs=min(4, len(seeds)), progress=not args.quiet)
    signals, skipped = {}, {}
    for name in _names(args.signals):
        # stac needs a chunked policy: it may come from --stac-policy; states are the task's either way
        owner, folder = (
            (load_policy(args.stac_policy)[0], args.stac_policy)
            if name == "stac" and args.stac_policy
            else (policy, args.policy)
        )
        try:
            signals[name] = _variant(owner, folder, name)
        except (SignalError, ValueError) as exc:
            skipped[name] = str(exc)
    result = bench_signals(signals, steps, args.robots, args.repeats, not args.quiet)
    if "stac" in result["signals"] and args.stac_policy:
        result["signals"]["stac"]["policy"] = str(args.stac_policy)
    out = {
        "benchmark": "signals",
        "policy": str(args.policy),
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "states_from": f"{task} rollouts, seeds {seeds[0]}..{seeds[-1]}",
        **result,
        "skipped": skipped,
    }
    print(json.dumps(stamped(out), indent=None if args.json else 2))
    return 0


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    from policy.hand_back import HAND_BACK

    p = sub.add_parser("train-signal", help="train a signal's auxiliary models (if any) and calibrate it")
    p.add_argument("--policy", required=True, type=Path, help="policy folder written by `hitl train`")
    p.add_argument("--signal", required=True, help="signal name (see policy.signals.SIGNALS)")
    p.add_argument("--data", required=True, type=Path, help="the demonstrations the policy was trained from")
    p.add_argument("--task", default=None, help="task for the policy's own rollouts (default: the policy's)")
    p.add_argument("--rollouts", type=int, default=20, help="policy rollouts for critics and rollout calibration")
    p.add_argument("--rollout-seed", type=int, default=3000, help="first rollout seed (disjoint from demos and evals)")
    p.add_argument("--envs", type=int, default=8)
    p.add_argument("--steps", type=int, default=None, help="training steps for auxiliary models")
    p.add_argument("--set", nargs="*", metavar="KEY=VALUE", help="signal config values, e.g. quantile=0.9")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train_signal)

    p = sub.add_parser(
        "assist", help="assisted rollouts: a driver signal calls the simulated operator, others in shadow"
    )
    p.add_argument("--policy", required=True, type=Path)
    p.add_argument("--task", default=None)
    p.add_argument("--driver", default="denoising")
    p.add_argument("--shadow", default=None, help="comma-separated signals scored in shadow, or 'all'")
    p.add_argument("--mode", choices=HAND_BACK, default="budgeted")
    p.add_argument("--budget", type=int, default=4, help="operator steps per assistance event (budgeted)")
    p.add_argument("--cooldown", type=int, default=0, help="policy steps after a hand-back without a new request")
    p.add_argument("--watchdog", type=float, default=None, help="also ask once at this fraction of the horizon")
    p.add_argument(
        "--hand-back-when-held",
        action="store_true",
        help="the operator hands back once the object is held (continuous: only then; budgeted: or at the budget)",
    )
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--envs", type=int, default=4)
    p.add_argument("--scores", action="store_true", help="include every signal's per-step scores")
    p.add_argument("--random-rate", type=float, default=None, help="help rate of the random reference")
    p.add_argument("--plot", type=Path, default=None, help="folder for the first episode's signal comparison figure")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", action="store_true", help="one line of JSON")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_assist)

    q = bench.add_parser("signals", help="cost per robot-step of every assistance signal")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument(
        "--stac-policy", type=Path, default=None, help="a chunked policy for stac (needs action_horizon > 1)"
    )
    q.add_argument(
        "--signals",
        default="all",
        help="comma-separated names, each as saved next to the policy, or NAME:key=value for one setting changed",
    )
    q.add_argument("--task", default=None)
    q.add_argument("--episodes", type=int, default=4)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--robots", type=int, default=8)
    q.add_argument("--repeats", type=int, default=5)
    q.add_argument("--threads", type=int, default=None)
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_signals)

"""``hitl train | rollout | calibrate | plot | report | bench``: the policy side of the CLI."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path


def _cmd_train(args: argparse.Namespace) -> int:
    import torch

    from policy.checkpoint import save_policy
    from policy.config import DiffusionPolicyConfig
    from policy.diffusion_policy import DiffusionPolicy
    from policy.frames import ObjectFrame
    from policy.train import TrainConfig, train_policy
    from sim.registry import make_task
    from storage.dataset import DatasetConfig, load_dataset
    from storage.paths import portable

    task = make_task(args.task)  # validates the name; the simulator is not built
    frame = ObjectFrame.from_obs_spec(task.obs_spec) if args.frame == "object" else None  # before any data
    ds = load_dataset(
        args.data, DatasetConfig(obs_horizon=args.obs_horizon, action_horizon=args.action_horizon, split_seed=args.seed)
    )
    if ds.obs.shape[1] != task.obs_spec.dim:
        raise ValueError(
            f"{args.data} holds {ds.obs.shape[1]}-dim observations, task {args.task} has "
            f"{task.obs_spec.dim}: was it recorded for another task or an older version?"
        )
    train_ep, val_ep = ds.split()
    cfg = DiffusionPolicyConfig(
        obs_dim=task.obs_spec.dim,
        obs_horizon=args.obs_horizon,
        action_horizon=args.action_horizon,
        n_action_steps=args.n_action_steps,
        network=args.network,
        down_dims=tuple(args.down_dims),
        num_inference_steps=args.ddim_steps,
        obs_encoder_dims=tuple(args.obs_encoder_dims),
        obs_fourier_octaves=(4 if args.obs_encoder_dims else 0)
        if args.obs_fourier_octaves is None
        else args.obs_fourier_octaves,
        object_frame=frame,
    )
    if args.symmetry_augment and task.symmetry_order < 2:
        raise ValueError(f"--symmetry-augment: task {args.task} has no scene symmetry to augment with")
    tcfg = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        threads=args.threads,
        symmetry_augment=args.symmetry_augment,
    )
    torch.manual_seed(args.seed)
    policy = DiffusionPolicy(cfg)
    # normalizer statistics come from the training episodes only
    train_idx = ds.sample_index(train_ep)
    # actions: over the task's workspace and the natural [-1, 1] of rotation and gripper
    bounds = (task.action_space.low, task.action_space.high)
    policy.fit_normalizers(ds.obs[train_idx[:, 0]], ds.actions[train_idx[:, 0]], action_bounds=bounds)
    ema, history = train_policy(
        policy,
        ds.arrays("train"),
        ds.arrays("val"),
        tcfg,
        progress=not args.quiet,
        symmetry=task.symmetric_observation,
        symmetry_order=task.symmetry_order,
    )
    info = {
        "task": args.task,
        "dataset": {
            "folder": portable(args.data),
            "episodes": ds.num_episodes,
            "train_episodes": [ds.names[i] for i in train_ep],
            "val_episodes": [ds.names[i] for i in val_ep],
            "val_episode_bytes": {ds.names[i]: (Path(args.data) / ds.names[i]).stat().st_size for i in val_ep},
            "split_seed": args.seed,
            "val_fraction": ds.config.val_fraction,
            "steps": int(len(ds.obs)),
            "excluded": ds.excluded,
        },
        "normalized_over": {  # the bounds themselves are in "normalization"
            "observation": "the training data's min/max per dimension",
            "action": f"the {args.task} workspace (position) and [-1, 1] (6D rotation, gripper)",
        },
        "training": {
            **tcfg.to_dict(),
            "seconds": round(history["seconds"], 1),
            "final_train_loss": history["train_loss"][-1],
            "final_val_loss": history["val_loss"][-1] if history["val_loss"] else None,
        },
        "command": "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        if args.command_line is None
        else args.command_line,
    }
    out = save_policy(ema, args.out, info)
    (out / "train_history.json").write_text(json.dumps(history) + "\n")
    print(
        json.dumps(
            {
                "out": str(out),
                "seconds": round(history["seconds"], 1),
                "train_loss": round(history["train_loss"][-1], 5),
                "val_loss": round(history["val_loss"][-1], 5) if history["val_loss"] else None,
            }
        )
    )
    return 0


_UNCERTAINTY_ARGS = {  # flag -> UncertaintyConfig field; the defaults live in UncertaintyConfig only
    "samples": "num_samples",
    "radius": "radius",
    "max_modes": "max_modes",
    "criterion": "criterion",
    "alpha": "alpha",
    "backend": "backend",
}


def _uncertainty_config(args: argparse.Namespace):
    from policy.uncertainty import UncertaintyConfig

    given = {f: getattr(args, a) for a, f in _UNCERTAINTY_ARGS.items() if getattr(args, a) is not None}
    return UncertaintyConfig(**given)


def _add_uncertainty_args(p: argparse.ArgumentParser) -> None:
    from policy.gmm import BACKENDS, CRITERIA
    from policy.uncertainty import UncertaintyConfig

    d = UncertaintyConfig()
    p.add_argument("--samples", type=int, help=f"probe samples S per robot (default {d.num_samples})")
    p.add_argument("--radius", type=float, help=f"probe radius r, normalized action space (default {d.radius})")
    p.add_argument("--max-modes", type=int, help=f"default {d.max_modes}")
    p.add_argument("--criterion", choices=list(CRITERIA), help=f"default {d.criterion}")
    p.add_argument("--alpha", type=float, help=f"default {d.alpha}")
    p.add_argument("--backend", choices=list(BACKENDS), help=f"default {d.backend}")


def _cmd_rollout(args: argparse.Namespace) -> int:

    from policy.evaluate import rollout_policy, summarize

    _set_threads(args)
    policy, info, calibration = _policy_with(args)
    uncertainty = None if args.no_uncertainty else _uncertainty_config(args)
    seeds = list(range(args.seed, args.seed + args.episodes))
    episodes, timing = rollout_policy(
        policy, args.task, seeds, n_envs=args.envs, uncertainty=uncertainty, progress=not args.quiet
    )
    out = {
        "policy": str(args.policy),
        "trained_on": info.get("task"),
        "task": args.task,
        **summarize(episodes),
        "seconds": round(timing["seconds"], 1),
    }
    if calibration and uncertainty is not None:
        thr = calibration["threshold"]
        above = [sum(u >= thr for u in e.uncertainty) for e in episodes]
        out["threshold"] = {
            "value": thr,
            "steps_above": int(sum(above)),
            "fraction_above": float(sum(above) / max(1, sum(e.steps for e in episodes))),
        }
    out["per_episode"] = [e.summary() for e in episodes]
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(
            f"{args.task}: {out['successes']}/{out['episodes']} successful "
            f"({out['success_rate']:.0%}), mean {out['steps']['mean']:.0f} steps"
        )
        if "uncertainty" in out:
            u = out["uncertainty"]
            print(f"uncertainty: median {u['median']:.3f}, p95 {u['p95']:.3f}, max {u['max']:.3f}")
    return 0


def _int_at_least(low: int):
    """An argparse type: an integer >= low, with a clear message otherwise."""

    def parse(text: str) -> int:
        value = int(text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse names the type in "invalid integer value: ..."
    return parse


_non_negative_int, _positive_int = _int_at_least(0), _int_at_least(1)


def _set_threads(args: argparse.Namespace) -> None:
    if getattr(args, "threads", None):
        import torch

        torch.set_num_threads(args.threads)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    _set_threads(args)
    from policy.calibrate import calibrate
    from policy.checkpoint import load_policy, save_calibration
    from policy.evaluate import rollout_check

    policy, info = load_policy(args.policy)
    config = _uncertainty_config(args)
    task = args.task or info.get("task")
    if args.rollouts and not task:
        raise ValueError(f"{args.policy}/config.json names no task: pass --task for the rollout check")
    record = calibrate(policy, info, args.data, args.quantile, config, progress=not args.quiet)
    if args.rollouts:
        record["rollout_check"] = rollout_check(
            policy,
            task,
            record["threshold"],
            config,
            episodes=args.rollouts,
            seed=args.rollout_seed,
            progress=not args.quiet,
        )
    path = save_calibration(args.policy, record)
    out = {
        "threshold": record["threshold"],
        "quantile": record["quantile"],
        "samples": record["samples"],
        "episodes": len(record["episodes"]),
        "validation_share_above": record["validation_share_above"],
        "saved": str(path),
    }
    check = record.get("rollout_check")
    if check:
        out["rollout_check"] = check
        if check["flagged"]:
            print(
                f"hitl calibrate: calibration problem: {check['share_above']:.0%} of the steps of "
                f"{check['episodes']} autonomous {check['task']} rollouts are above the threshold "
                f"(validation: {record['validation_share_above']:.0%}; flagged above {check['flag_share']:.0%})",
                file=sys.stderr,
            )
    print(json.dumps(out))
    return 0


def _policy_with(args: argparse.Namespace):
    """Loads the policy (optionally with another DDIM step count) and its calibration."""
    from dataclasses import replace

    from policy.checkpoint import load_calibration, load_policy
    from policy.diffusion_policy import DiffusionPolicy

    policy, info = load_policy(args.policy)
    if getattr(args, "ddim_steps", None):
        state = policy.state_dict()
        policy = DiffusionPolicy(replace(policy.config, num_inference_steps=args.ddim_steps))
        policy.load_state_dict(state)
        policy.eval()
    return policy, info, load_calibration(args.policy)


def _cmd_plot(args: argparse.Namespace) -> int:
    import numpy as np

    from bench.figures import plot_field, plot_timeline
    from policy.evaluate import context_for, rollout_policy

    policy, info, calibration = _policy_with(args)
    threshold = calibration["threshold"] if calibration else None
    seeds = list(range(args.seed, args.seed + args.episodes))
    episodes, _ = rollout_policy(
        policy,
        args.task,
        seeds,
        n_envs=min(4, len(seeds)),
        uncertainty=_uncertainty_config(args),
        keep_fields=True,
        progress=not args.quiet,
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
    text = json.dumps(report, indent=2)
    path = args.report or out / f"{args.task}-uncertainty.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n")
    print(text if args.json else f"wrote {timeline} and {field}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import numpy as np

    from bench.uncertainty import bench_uncertainty
    from policy.devices import prepare_for_serving
    from policy.evaluate import rollout_policy
    from policy.signals import SignalError, load_signal

    _set_threads(args)
    policy, info, _ = _policy_with(args)
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
    episodes, _ = rollout_policy(
        policy,
        task,
        seeds,
        n_envs=min(4, len(seeds)),
        uncertainty=_uncertainty_config(args),
        keep_fields=True,
        progress=not args.quiet,
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
        _uncertainty_config(args),
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
    print(json.dumps(result, indent=2 if not args.json else None))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    _set_threads(args)
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
        Path(args.out).with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    print(text)
    return 0


def _cmd_separation(args: argparse.Namespace) -> int:
    _set_threads(args)
    from bench.separation import shift_separation
    from policy.checkpoint import load_policy

    policy, info = load_policy(args.policy)
    in_task = args.in_task or info.get("task")
    if not in_task:
        raise ValueError(f"{args.policy}/config.json names no task: pass --in-task")
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
    doc = {"command": "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:]), **report.to_dict()}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(doc, indent=2) + "\n")
    print(report.markdown())
    return 0


def register(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """Adds the policy commands; returns the ``bench`` targets for other command groups."""
    p = sub.add_parser("train", help="train a diffusion policy on recorded demonstrations")
    p.add_argument("--task", required=True)
    p.add_argument("--data", required=True, type=Path, help="folder of MCAP episodes")
    p.add_argument("--out", required=True, type=Path, help="policy folder to write")
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--network", choices=["unet", "mlp"], default="unet")
    p.add_argument("--down-dims", type=int, nargs="+", default=[64, 128])
    p.add_argument("--obs-encoder-dims", type=int, nargs="*", default=[256, 256])
    p.add_argument("--obs-horizon", type=int, default=1)
    p.add_argument("--action-horizon", type=int, default=1)
    p.add_argument("--n-action-steps", type=int, default=None)
    p.add_argument("--ddim-steps", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: all)")
    p.add_argument(
        "--obs-fourier-octaves",
        type=int,
        default=None,
        help="feed the observation encoder sin/cos of each observation at this many octave frequencies "
        "(default 4 with an observation encoder, 0 without; 0 turns them off)",
    )
    p.add_argument(
        "--symmetry-augment",
        action="store_true",
        help="train on observations turned into random identical poses of the scene (lift-cube: quarter turns)",
    )
    p.add_argument(
        "--frame",
        choices=["world", "object"],
        default="world",
        help="the frame the network sees observations and predicts actions in: the world, or the object's "
        "position and heading on the table (tasks that observe object_pos and object_rot6d)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train, command_line=None)

    p = sub.add_parser("rollout", help="run a policy autonomously; success, steps and uncertainty")
    p.add_argument("--policy", required=True, type=Path, help="policy folder written by `hitl train`")
    p.add_argument("--task", required=True)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=1000, help="first episode seed (demonstrations use 0..)")
    p.add_argument("--envs", type=int, default=4, help="simulated robots stepping in lockstep")
    p.add_argument("--ddim-steps", type=int, default=None, help="override the policy's DDIM steps")
    p.add_argument("--no-uncertainty", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")
    _add_uncertainty_args(p)
    p.set_defaults(func=_cmd_rollout)

    p = sub.add_parser("calibrate", help="uncertainty threshold from the held-out validation episodes")
    p.add_argument("--policy", required=True, type=Path)
    p.add_argument("--data", required=True, type=Path, help="the folder the policy was trained from")
    p.add_argument("--quantile", type=float, default=0.95)
    p.add_argument(
        "--rollouts",
        type=_non_negative_int,
        default=10,
        help="autonomous rollouts on which to measure the share of steps above the threshold (0: none)",
    )
    p.add_argument("--rollout-seed", type=int, default=3000, help="first seed of those rollouts")
    p.add_argument("--task", default=None, help="task of those rollouts (default: the policy's training task)")
    p.add_argument("--threads", type=_positive_int, default=None, help="torch CPU threads (default: all)")
    p.add_argument("--quiet", action="store_true")
    _add_uncertainty_args(p)
    p.set_defaults(func=_cmd_calibrate)

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
    _add_uncertainty_args(q)
    q.set_defaults(func=_cmd_plot)

    p = sub.add_parser("report", help="run the paper's sanity checks and write them to docs/results/")
    what = p.add_subparsers(dest="report", required=True)
    q = what.add_parser("sanity", help="lift on seen/unseen objects, cup-stack grasp vs insertion, drawer choice")
    q.add_argument("--lift", type=Path, help="lift-cube policy folder")
    q.add_argument("--cup", type=Path, help="cup-stack policy folder")
    q.add_argument("--drawer", type=Path, help="open-drawer policy folder")
    q.add_argument("--episodes-lift", type=_positive_int, default=50)
    q.add_argument("--episodes-other", type=_positive_int, default=50, help="per unseen lift object")
    q.add_argument("--episodes-cup", type=_positive_int, default=50)
    q.add_argument("--episodes-drawer", type=_positive_int, default=50)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--out", type=Path, help="markdown file (a .json with the numbers is written beside it)")
    q.add_argument("--threads", type=_positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_report)
    q = what.add_parser("separation", help="AUROC of every signal for shifted vs training-distribution states")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--in-task", default=None, help="training-distribution task (default: the policy's)")
    q.add_argument("--shift-tasks", nargs="+", default=["lift-nut", "lift-hammer", "lift-hook"])
    q.add_argument("--episodes", type=_positive_int, default=8, help="rollouts per task")
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--signals", nargs="+", default=None, help="default: every registered signal")
    q.add_argument("--out", type=Path, help="JSON file to write (the markdown table is printed)")
    q.add_argument("--threads", type=_positive_int, default=None, help="torch CPU threads (default: all)")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_separation)

    p = sub.add_parser("bench", help="speed measurements, printed as JSON")
    what = p.add_subparsers(dest="target", required=True)
    q = what.add_parser("uncertainty", help="uncertainty metric vs DDIM sampling; torch vs sklearn GMM")
    q.add_argument("--policy", required=True, type=Path)
    q.add_argument("--task", default=None, help="task to collect rollout states on (default: the policy's)")
    q.add_argument("--episodes", type=int, default=4)
    q.add_argument("--seed", type=int, default=1000)
    q.add_argument("--fleet-sizes", type=_positive_int, nargs="+", default=[1, 8, 16, 32])
    q.add_argument("--repeats", type=_positive_int, default=5)
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
    _add_uncertainty_args(q)
    q.set_defaults(func=_cmd_bench)
    return what

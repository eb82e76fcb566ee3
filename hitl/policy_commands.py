"""``hitl train | rollout | calibrate``: training a policy, running it, and calibrating its threshold."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from hitl.args import add_uncertainty_args, non_negative_int, policy_with, positive_int, set_threads, uncertainty_config


def _cmd_train(args: argparse.Namespace) -> int:
    import torch

    from policy.checkpoint import check_fits, layout_info, save_policy
    from policy.config import DiffusionPolicyConfig
    from policy.diffusion_policy import DiffusionPolicy
    from policy.frames import ObjectFrame
    from policy.heldout import episode_digest
    from policy.train import TrainConfig, train_policy
    from sim.demos import read_recipe
    from sim.registry import make_task
    from sim.vision import CameraSpec
    from storage.dataset import DatasetConfig, load_dataset
    from storage.obs_layout import describe, mismatched
    from storage.paths import portable

    make_task(args.task)  # validates the name; the simulator is not built
    ds = load_dataset(
        args.data, DatasetConfig(obs_horizon=args.obs_horizon, action_horizon=args.action_horizon, split_seed=args.seed)
    )
    # episodes with frames train a policy that sees them, on the task as such a policy observes it
    task = make_task(args.task, images=bool(ds.cameras))
    cameras = tuple(CameraSpec.from_json(c) for c in ds.cameras)
    if cameras and (lacks := sorted({c.name for c in cameras} - {c.name for c in task.cameras})):
        raise ValueError(f"{args.data} holds frames of cameras {lacks} that task {args.task} does not declare")
    if cameras and args.frame == "object":
        raise ValueError(f"{args.data} holds camera frames: a policy that sees cameras has no object frame")
    frame = ObjectFrame.from_obs_spec(task.obs_spec) if args.frame == "object" else None
    if other := mismatched(zip(ds.names, ds.meta, strict=True), task.obs_spec.labels()):
        name, why = next(iter(other.items()))
        raise ValueError(
            f"{len(other)} episode(s) of {args.data} were recorded with another observation layout than task "
            f"{args.task}'s {describe(task.obs_spec.labels())}, e.g. {name}: {why}"
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
        cameras=cameras,
        image_channels=args.image_channels,
    )
    check_fits({"policy": cfg.to_dict(), **layout_info(task.obs_spec)}, args.task, args.out)  # before training
    if args.symmetry_augment and task.symmetry_order < 2:
        raise ValueError(f"--symmetry-augment: task {args.task} has no scene symmetry to augment with")
    tcfg = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        threads=args.threads,
        symmetry_augment=args.symmetry_augment,
        origin_jitter=args.origin_jitter,
        height_jitter=args.height_jitter,
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
        **layout_info(task.obs_spec),  # the observation layout it is trained on: check_fits compares it
        "dataset": {
            "folder": portable(args.data),
            "episodes": ds.num_episodes,
            "train_episodes": [ds.names[i] for i in train_ep],
            "val_episodes": [ds.names[i] for i in val_ep],
            # what identifies them (policy.heldout): their steps' digest, not their files
            "val_episode_digest": {ds.names[i]: episode_digest(ds, i) for i in val_ep},
            "split_seed": args.seed,
            "val_fraction": ds.config.val_fraction,
            "steps": int(len(ds.obs)),
            "excluded": ds.excluded,
            # how to record the folder again (a fine-tuning job does, on a machine without it)
            "recipe": recipe.to_dict() if (recipe := read_recipe(args.data)) is not None else None,
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


def _cmd_rollout(args: argparse.Namespace) -> int:

    from bench.provenance import stamped
    from policy.evaluate import rollout_policy, summarize

    set_threads(args)
    policy, info, calibration = policy_with(args)
    uncertainty = None if args.no_uncertainty else uncertainty_config(args)
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
        print(json.dumps(stamped(out), indent=2))
    else:
        print(
            f"{args.task}: {out['successes']}/{out['episodes']} successful "
            f"({out['success_rate']:.0%}), mean {out['steps']['mean']:.0f} steps"
        )
        if "uncertainty" in out:
            u = out["uncertainty"]
            print(f"uncertainty: median {u['median']:.3f}, p95 {u['p95']:.3f}, max {u['max']:.3f}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    set_threads(args)
    from policy.calibrate import calibrate
    from policy.checkpoint import check_fits, load_policy, save_calibration
    from policy.evaluate import rollout_check

    policy, info = load_policy(args.policy)
    config = uncertainty_config(args)
    task = args.task or info.get("task")
    if args.rollouts and not task:
        raise ValueError(f"{args.policy}/config.json names no task: pass --task for the rollout check")
    if args.rollouts:
        check_fits(info, task, args.policy)
    cal = calibrate(policy, info, args.data, args.quantile, config, progress=not args.quiet)
    record = cal.to_dict()
    check = None
    if args.rollouts:
        check = record["rollout_check"] = rollout_check(
            policy,
            task,
            cal.threshold,
            config,
            episodes=args.rollouts,
            seed=args.rollout_seed,
            progress=not args.quiet,
        )
    path = save_calibration(args.policy, record)
    out = {
        "threshold": cal.threshold,
        "quantile": cal.quantile,
        "samples": cal.samples,
        "episodes": len(cal.episodes),
        "validation_share_above": cal.validation_share_above,
        "saved": str(path),
    }
    if check:
        out["rollout_check"] = check
        if check["flagged"]:
            print(
                f"hitl calibrate: calibration problem: {check['share_above']:.0%} of the steps of "
                f"{check['episodes']} autonomous {check['task']} rollouts are above the threshold "
                f"(validation: {cal.validation_share_above:.0%}; flagged above {check['flag_share']:.0%})",
                file=sys.stderr,
            )
    print(json.dumps(out))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument(
        "--image-channels", type=int, default=32, help="width of each camera's encoder (episodes with frames)"
    )
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
        "--origin-jitter",
        type=float,
        default=0.0,
        help="metres: each training sample sees its object up to this far from where it is across the table (x, y), "
        "so that what the policy does near an object follows what it senses there (finger_rays), not the "
        "object's origin (--frame object only; default 0: off)",
    )
    p.add_argument(
        "--height-jitter",
        type=float,
        default=0.0,
        help="metres: each training sample sees its end effector and its targets up to this far higher or lower "
        "against the object, so that the height the policy holds near an object follows what it senses there "
        "(--frame object only; default 0: off)",
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
    add_uncertainty_args(p)
    p.set_defaults(func=_cmd_rollout)

    p = sub.add_parser("calibrate", help="uncertainty threshold from the held-out validation episodes")
    p.add_argument("--policy", required=True, type=Path)
    p.add_argument("--data", required=True, type=Path, help="the folder the policy was trained from")
    p.add_argument("--quantile", type=float, default=0.95)
    p.add_argument(
        "--rollouts",
        type=non_negative_int,
        default=10,
        help="autonomous rollouts on which to measure the share of steps above the threshold (0: none)",
    )
    p.add_argument("--rollout-seed", type=int, default=3000, help="first seed of those rollouts")
    p.add_argument("--task", default=None, help="task of those rollouts (default: the policy's training task)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all)")
    p.add_argument("--quiet", action="store_true")
    add_uncertainty_args(p)
    p.set_defaults(func=_cmd_calibrate)

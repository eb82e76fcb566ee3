"""``hitl policy list | promote | rollback`` and ``hitl finetune``: the registry and the fine-tuning job.

Both work on the service's metadata store and data folder (``--config``, ``HITL_DATA_DIR``,
``DATABASE_URL``), with or without the service running: a running fleet follows the registry and
hot-swaps at each robot's next episode.

``hitl finetune`` exit codes: 0 done (or nothing to do), 1 a job failed, 2 bad input (nothing
changed), 3 another job holds the lease (try later), 130 interrupted (SIGTERM, Ctrl-C: resumable).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import sys
from pathlib import Path

from hitl.args import add_store_args, fail, open_store

EXIT_FAILED, EXIT_BUSY, EXIT_INTERRUPTED = 1, 3, 130


def _version_doc(row) -> dict:
    tasks = (row.evaluation or {}).get("tasks", {})
    return {
        "ref": row.ref,
        "id": row.id,
        "status": row.status,
        "task": row.task,
        "threshold": row.threshold,
        "parent_id": row.parent_id,
        "created_at": row.created_at.isoformat(timespec="seconds"),
        "path": row.path,
        "evaluation": {t: d.get("success_rate") for t, d in tasks.items()},
        "reason": row.status_reason,
        "command": row.command,
    }


def _cmd_policy_list(args: argparse.Namespace) -> int:
    from server import registry
    from server.errors import ServiceError

    _, sessions = open_store(args)
    try:
        rows = registry.versions(sessions, args.name)
    except ServiceError as exc:
        return fail("policy list", exc)
    docs = [_version_doc(r) for r in rows]
    if args.json:
        print(json.dumps(docs, indent=2))
        return 0
    if not docs:
        print("no policy version is registered (hitl serve registers the configured ones)")
    for d in docs:
        ev = ", ".join(f"{t} {v:.2f}" for t, v in d["evaluation"].items()) or "not evaluated"
        thr = f"{d['threshold']:.4g}" if d["threshold"] is not None else "-"
        print(f"{d['ref']:<24} {d['status']:<9} task {d['task']:<12} threshold {thr:<9} {d['created_at']}  {ev}")
        if d["reason"]:
            print(f"{'':<24} {d['reason']}")
    return 0


def _cmd_policy_promote(args: argparse.Namespace) -> int:
    from server import registry
    from server.errors import ServiceError

    _, sessions = open_store(args)
    try:
        ref = registry.PolicyRef.parse(args.ref)
        if ref.version is None:
            raise ServiceError(422, f"promote which version? give NAME@VERSION, e.g. {ref.name}@2")
        row = registry.promote(sessions, ref, args.reason or "promoted with hitl policy promote")
    except ServiceError as exc:
        return fail("policy promote", exc)
    print(json.dumps({"active": row.ref, "path": row.path}))
    return 0


def _cmd_policy_rollback(args: argparse.Namespace) -> int:
    from server import registry
    from server.errors import ServiceError

    _, sessions = open_store(args)
    try:
        row = registry.rollback(sessions, registry.PolicyRef.parse(args.name).name, args.reason)
    except ServiceError as exc:
        return fail("policy rollback", exc)
    print(json.dumps({"active": row.ref, "path": row.path}))
    return 0


def _finetune_config(args: argparse.Namespace, settings):
    from policy.finetune import FinetuneConfig

    ft = settings.finetune
    given = {"eval_episodes": ft.eval_episodes, "tolerance": ft.tolerance, "min_gain": ft.min_gain}
    given |= {"eval_seed": ft.eval_seed, "steps": ft.steps, "fit_episodes": ft.fit_episodes, "fit_seed": ft.fit_seed}
    given["widen_obs_range"] = ft.widen_obs_range and not args.keep_obs_range
    given["successful_only"] = ft.successful_only if args.successful_only is None else args.successful_only
    given["takeover_tail"] = ft.takeover_tail if args.takeover_tail is None else (args.takeover_tail or None)
    given |= {
        k: getattr(args, k)
        for k in ("ratio", "steps", "batch_size", "lr", "seed", "eval_seed", "tolerance", "min_gain", "eval_episodes")
        if getattr(args, k) is not None
    }
    return FinetuneConfig(**given)


def _lineage_selection(args: argparse.Namespace, settings) -> dict[str, tuple[bool, int | None]]:
    """``[finetune.selection]``, lineage by lineage, unless the command line chose the takeovers itself."""
    if args.successful_only is not None or args.takeover_tail is not None:
        return {}
    return {name: (c.successful_only, c.takeover_tail) for name, c in settings.finetune.selection.items()}


def _command_line(argv: list[str]) -> str:
    """The command as recorded in the registry (readable by viewers): a database URL is left out."""
    out, skip = [], False
    for a in argv:
        if skip:
            out.append("***")
            skip = False
        elif a == "--database-url":
            out.append(a)
            skip = True
        elif a.startswith("--database-url="):
            out.append("--database-url=***")
        else:
            out.append(a)
    return "hitl " + " ".join(shlex.quote(a) for a in out)


def _interrupted(signum, frame) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _cmd_finetune(args: argparse.Namespace) -> int:
    import logging

    import torch

    from server.errors import ServiceError
    from server.finetune.job import FinetuneRunner, JobBusy
    from server.finetune.plan import JobRequest, parse_since
    from server.lease import LeaseLost

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.nice:
        os.nice(args.nice)  # below the fleet: the service starts its jobs this way
    if args.idle_priority and hasattr(os, "SCHED_IDLE"):  # Linux: the CPU only when nothing else wants it
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    try:
        settings, sessions = open_store(args)
        torch.set_num_threads(args.threads or settings.finetune.threads)
        request = JobRequest(
            policy=args.policy,
            since=parse_since(args.since) if args.since else None,
            source=args.source,
            episodes=args.episodes,
            pretrain_data=args.pretrain_data,
            eval_tasks=tuple(args.eval_tasks) if args.eval_tasks else None,
            promote=settings.finetune.promote if args.promote is None else args.promote,
            config=_finetune_config(args, settings),
            trigger=args.trigger,
            command=_command_line(sys.argv[1:]),
            job_id=args.job,
            lease_ttl=settings.finetune.lease_seconds,
            selection=_lineage_selection(args, settings),
        )
        runner = FinetuneRunner(
            sessions,
            settings.data_dir,
            settings.finetune.eval_tasks,
            progress=not args.quiet,
            report=lambda line: print(line, flush=True),
        )
        # a SIGTERM (systemd, Kubernetes, the service stopping) ends the job as "interrupted", resumable
        signal.signal(signal.SIGTERM, _interrupted)
        results = runner.run(request)
    except (JobBusy, LeaseLost) as exc:
        print(f"hitl finetune: {exc}", file=sys.stderr)
        return EXIT_BUSY
    except KeyboardInterrupt:
        print("hitl finetune: interrupted; the job resumes from its last checkpoint at the next run", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ServiceError, ValueError, FileNotFoundError, KeyError) as exc:
        return fail("finetune", exc)
    return EXIT_FAILED if any(r["status"] != "succeeded" for r in results) else 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("policy", help="the policy registry: list, promote, roll back")
    verbs = p.add_subparsers(dest="verb", required=True)
    q = verbs.add_parser("list", help="every version with its status, threshold, evaluation and reason")
    q.add_argument("name", nargs="?", default=None, help="one lineage only")
    q.add_argument("--json", action="store_true")
    add_store_args(q)
    q.set_defaults(func=_cmd_policy_list)
    q = verbs.add_parser("promote", help="make NAME@VERSION active (a running fleet swaps at each next episode)")
    q.add_argument("ref", help="NAME@VERSION")
    q.add_argument("--reason", default=None)
    add_store_args(q)
    q.set_defaults(func=_cmd_policy_promote)
    q = verbs.add_parser("rollback", help="retire NAME's active version and make its parent active again")
    q.add_argument("name")
    q.add_argument("--reason", default=None)
    add_store_args(q)
    q.set_defaults(func=_cmd_policy_rollback)

    p = sub.add_parser(
        "finetune",
        help="fine-tune on takeover segments, recalibrate, evaluate, gate (exit 3: another job is running)",
    )
    p.add_argument("--policy", default=None, help="NAME[@active|@VERSION]; default: every lineage with new takeovers")
    p.add_argument("--since", default=None, help="only segments that ended within this window: 30m, 24h, 7d")
    p.add_argument("--source", choices=["takeovers", "full-episodes"], default="takeovers")
    p.add_argument("--episodes", type=Path, default=None, help="--source full-episodes: a folder of episode MCAPs")
    p.add_argument("--pretrain-data", type=Path, default=None, help="default: the folder in the policy's config.json")
    p.add_argument("--eval-tasks", nargs="+", default=None, help="the gate's target tasks (default: the takeovers')")
    p.add_argument("--eval-episodes", type=int, default=None, help="per task (default: settings, 20)")
    p.add_argument("--eval-seed", type=int, default=None)
    p.add_argument("--ratio", type=float, default=None, help="takeover share of each mini-batch (default 0.5)")
    p.add_argument(
        "--keep-obs-range",
        action="store_true",
        help="keep the parent's observation range (default: widen it to cover the takeover data)",
    )
    p.add_argument(
        "--successful-only",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="only takeovers in episodes that ended in success (default: settings, off)",
    )
    p.add_argument(
        "--takeover-tail",
        type=int,
        default=None,
        metavar="N",
        help="only the last N steps of each takeover, those that led to the hand-back (0: every step; "
        "default: settings, every step)",
    )
    p.add_argument("--steps", type=int, default=None, help="fixed step count (default: scales with the data)")
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--tolerance", type=float, default=None, help="allowed drop on the training task (settings: 0.05)")
    p.add_argument("--min-gain", type=float, default=None, help="required rise on the target tasks (settings: 0)")
    p.add_argument(
        "--promote",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="promote a version that passes the gate (default: settings, on)",
    )
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--nice", type=int, default=0, help="lower this process's CPU priority by N (os.nice)")
    p.add_argument(
        "--idle-priority", action="store_true", help="run under SCHED_IDLE: only on CPU time nothing else wants"
    )
    p.add_argument("--trigger", default="cli", help=argparse.SUPPRESS)
    p.add_argument("--job", type=int, default=None, help=argparse.SUPPRESS)  # a queued job row (the API's)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_store_args(p)
    p.set_defaults(func=_cmd_finetune)

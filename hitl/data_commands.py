"""``hitl export lerobot`` and ``hitl import lerobot``: our episodes and takeovers as a LeRobotDataset
(v3.0 layout), and a LeRobotDataset as demonstrations ``hitl train`` takes. Each prints a JSON report.
"""

from __future__ import annotations

import argparse
import json
from datetime import UTC, datetime
from pathlib import Path

from hitl.args import add_store_args, fail, open_store, positive_int


def _when(text: str) -> datetime:
    try:
        when = datetime.fromisoformat(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an ISO 8601 time: {text!r}") from exc
    return when if when.tzinfo is not None else when.replace(tzinfo=UTC)


def _cmd_export(args: argparse.Namespace) -> int:
    from server.errors import ServiceError
    from sim.registry import TASKS, make_task
    from sim.spaces import ACTION_LABELS
    from storage.episodes import EpisodeReadError
    from storage.lerobot.attempts import from_folder
    from storage.lerobot.layout import ExportError, write_dataset

    progress = not args.quiet
    skipped: dict[str, str] = {}
    try:
        if args.demos is not None:
            if args.takeovers_only:
                raise ExportError("--takeovers-only selects fleet takeovers; a --demos folder has none")
            attempts = from_folder(args.demos, task=args.task)
        else:
            from server.export import ExportQuery, collect
            from server.finetune.plan import parse_since

            settings, sessions = open_store(args)
            since = args.start
            if args.since:
                since = datetime.now(UTC) - parse_since(args.since)
            query = ExportQuery(
                task=args.task,
                lineage=args.lineage,
                since=since,
                until=args.until,
                episode_ids=tuple(args.episode or ()),
                segment_ids=tuple(args.segment or ()),
                takeovers_only=args.takeovers_only,
            )
            collected = collect(sessions, settings.data_dir, query, progress)
            attempts, skipped = collected.attempts, collected.skipped
        texts = {name: make_task(name).description for name in {a.task for a in attempts} if name in TASKS}
        report = write_dataset(
            attempts,
            args.out,
            fps=args.fps,
            action_labels=list(ACTION_LABELS),
            task_texts=texts,
            robot_type=args.robot_type,
            chunks_size=args.chunks_size,
            data_files_size_in_mb=args.file_size_mb,
            overwrite=args.overwrite,
            progress=progress,
        )
    except (ExportError, ServiceError, EpisodeReadError, FileNotFoundError, ValueError) as exc:
        return fail("export lerobot", exc)
    print(json.dumps(report.as_dict() | {"skipped": skipped}, indent=2))
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from sim.registry import TASKS, make_task
    from sim.spaces import ACTION_LABELS
    from storage.lerobot.reader import LeRobotImportError, image_features, import_dataset, read_info

    if args.task not in TASKS:
        return fail("import lerobot", ValueError(f"unknown task {args.task!r}; registered: {', '.join(TASKS)}"))
    try:  # a dataset with camera features is imported for a policy that sees: the task observed as one does
        sees = bool(image_features(read_info(args.root)))
    except LeRobotImportError as exc:
        return fail("import lerobot", exc)
    task = make_task(args.task, images=sees)
    spec = task.obs_spec
    pose = spec.ee_pose if spec.has_ee_pose else None
    try:
        report = import_dataset(
            args.root,
            args.out,
            args.task,
            spec.labels(),
            list(ACTION_LABELS),
            pose_from_state=pose,
            overwrite=args.overwrite,
            progress=not args.quiet,
            cameras=[c.to_json() for c in task.cameras] if sees else [],
        )
    except (LeRobotImportError, OSError) as exc:
        return fail("import lerobot", exc)
    print(json.dumps(report.as_dict(), indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="episodes and takeovers as a dataset for other training stacks")
    formats = p.add_subparsers(dest="format", required=True)
    q = formats.add_parser(
        "lerobot",
        help="write a LeRobotDataset (v3.0 layout): whole task attempts with their takeovers marked, or takeovers",
    )
    q.add_argument("out", type=Path, help="the dataset folder to write")
    q.add_argument("--demos", type=Path, default=None, help="export this folder of episode MCAPs instead of fleet data")
    add_store_args(q)
    q.add_argument("--task", default=None, help="only this task")
    q.add_argument("--lineage", default=None, help="only episodes and takeovers of this policy name (any version)")
    window = q.add_mutually_exclusive_group()
    window.add_argument("--since", default=None, help="only what started within this window: 30m, 24h, 7d")
    window.add_argument("--from", dest="start", type=_when, default=None, help="only what started from then (ISO 8601)")
    q.add_argument("--until", type=_when, default=None, help="only what started before (ISO 8601)")
    q.add_argument("--episode", type=int, action="append", help="this fleet episode id (repeatable)")
    q.add_argument("--segment", type=int, action="append", help="this takeover segment id (repeatable)")
    q.add_argument("--takeovers-only", action="store_true", help="each takeover as an episode of its own")
    q.add_argument("--fps", type=positive_int, default=20, help="frames per second (the control rate: 20)")
    q.add_argument("--robot-type", default="panda", help="info.json's robot_type")
    q.add_argument("--chunks-size", type=positive_int, default=1000, help="data files per chunk folder")
    q.add_argument("--file-size-mb", type=float, default=100.0, help="about this many MB per data file")
    q.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    q.add_argument("--quiet", action="store_true", help="no progress bars")
    q.set_defaults(func=_cmd_export)

    p = sub.add_parser("import", help="a dataset from another training stack as demonstrations")
    formats = p.add_subparsers(dest="format", required=True)
    q = formats.add_parser("lerobot", help="a LeRobotDataset (v3.0) with our state and action layout, as MCAP demos")
    q.add_argument("root", type=Path, help="the dataset folder (meta/info.json, data/...)")
    q.add_argument("out", type=Path, help="the folder of MCAP episodes to write (what hitl train takes)")
    q.add_argument("--task", required=True, help="the task whose observation and action the dataset holds")
    q.add_argument("--overwrite", action="store_true", help="write into a folder that already holds episodes")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=_cmd_import)

"""``hitl serve | token``: the fleet service side of the CLI."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def _settings(args: argparse.Namespace):
    from server.settings import Settings

    overrides = {k: v for k, v in (("host", getattr(args, "host", None)), ("port", getattr(args, "port", None))) if v}
    return Settings.load(args.config, **overrides)


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from server.app import RedactTokens, create_app

    settings = _settings(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("uvicorn.access").addFilter(RedactTokens())
    print(f"hitl: API docs at http://{settings.host}:{settings.port}/docs", flush=True)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    return 0


def _cmd_token(args: argparse.Namespace) -> int:
    from server.auth import create_token, revoke_token
    from server.db import make_engine, migrate, session_factory

    settings = _settings(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    if args.action == "create":
        token = create_token(sessions, args.name, args.role)
        print(token)  # shown once; only its hash is stored
    else:
        if not revoke_token(sessions, args.name):
            raise KeyError(f"no token named {args.name!r}")
        print(f"revoked {args.name}")
    return 0


def _cmd_operator_bot(args: argparse.Namespace) -> int:
    from server.operator_bot import OperatorBot

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise
    bot = OperatorBot(args.url, args.token)
    try:
        bot.run(max_takeovers=args.takeovers)
    except KeyboardInterrupt:
        pass
    finally:
        bot.close()
    print(f"takeovers: {bot.takeovers}, commands: {bot.commands}")
    return 0


def _cmd_bench_fleet(args: argparse.Namespace) -> int:
    import json

    from server.bench import bench_fleet

    sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    if not sizes or any(n < 1 or n > 64 for n in sizes):
        raise ValueError(f"--robots must be a comma-separated list of sizes in 1..64, got {args.robots!r}")
    if not (0 < args.command_hz <= 1000):
        raise ValueError(f"--command-hz must be in (0, 1000], got {args.command_hz!r}")
    result = bench_fleet(
        args.task,
        sizes,
        args.seconds,
        progress=not args.quiet,
        torch_threads=args.torch_threads,
        command_hz=args.command_hz,
    )
    print(json.dumps(result, indent=None if args.json else 2))
    return 0


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    from server.auth import ROLES

    p = sub.add_parser("serve", help="run the fleet service (REST API, assistance queue, simulated fleet)")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--config", type=Path, default=None, help="TOML settings file (HITL_* variables override it)")
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("operator-bot", help="simulated operator: claims queued robots and drives them via the API")
    p.add_argument("--url", required=True, help="service URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", required=True, help="an operator token")
    p.add_argument("--takeovers", type=int, default=None, help="stop after this many takeovers")
    p.set_defaults(func=_cmd_operator_bot)

    q = bench.add_parser("fleet", help="fleet throughput against raw physics; command latency")
    q.add_argument("--robots", default="1,4,8,16")
    q.add_argument("--task", default="lift-cube")
    q.add_argument("--seconds", type=float, default=10.0)
    q.add_argument("--torch-threads", type=int, default=1, help="server-side torch threads (the setting)")
    q.add_argument("--command-hz", type=float, default=30.0, help="the bench operator's command stream rate")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_fleet)

    p = sub.add_parser("token", help="create or revoke API tokens")
    p.add_argument("action", choices=["create", "revoke"])
    p.add_argument("--name", required=True)
    p.add_argument("--role", choices=ROLES, default="viewer")
    p.add_argument("--config", type=Path, default=None)
    p.set_defaults(func=_cmd_token)

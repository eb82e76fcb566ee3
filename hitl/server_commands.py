"""``hitl serve | token``: the fleet service side of the CLI."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def _settings(args: argparse.Namespace):
    from server.settings import Settings

    given = (("host", getattr(args, "host", None)), ("port", getattr(args, "port", None)))
    overrides = {k: v for k, v in given if v}
    if getattr(args, "api_workers", None) is not None:
        overrides["api_workers"] = args.api_workers
    return Settings.load(args.config, **overrides)


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.app import create_app

    settings = _settings(args)
    # one format for the service's and uvicorn's lines (log_config=None: uvicorn's loggers propagate here);
    # the app's lifespan adds token redaction and sends successful polling GETs to debug (server.app)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.log_level == "debug":
        logging.getLogger("hitl").setLevel(logging.DEBUG)
    if settings.api_workers:  # the API in processes of its own, the fleet runtime in this one
        from service.replicas import serve

        return serve(settings, settings.api_workers, args.log_level)
    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level, log_config=None)
    server = uvicorn.Server(config)
    app.state.server = server  # the "ready: ..." line names the address this server bound
    server.run()
    return 0 if server.started else 1


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
    from client.operator_bot import OperatorBot

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise
    bot = OperatorBot(args.url, args.token, hands_back_when_held=args.hand_back_when_held)
    try:
        bot.run(max_takeovers=args.takeovers)
    except KeyboardInterrupt:
        pass
    finally:
        bot.close()
    print(f"takeovers: {bot.takeovers}, commands: {bot.commands}")
    return 0


def _cmd_bench_finetune_load(args: argparse.Namespace) -> int:
    import json

    from bench.finetune_load import bench_finetune_load
    from bench.provenance import stamped

    result = bench_finetune_load(
        robots=args.robots,
        task=args.task,
        control_hz=args.control_hz,
        idle_seconds=args.idle_seconds,
        seconds=args.seconds,
        niceness=args.niceness,
        idle_priority=not args.no_idle_priority,
        progress=not args.quiet,
    )
    text = json.dumps(stamped(result), indent=None if args.json else 2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


def _cmd_bench_fleet(args: argparse.Namespace) -> int:
    import json

    from bench.fleet import bench_fleet
    from bench.provenance import stamped
    from policy.devices import check_device
    from server.settings import Settings

    sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    if not sizes or any(n < 1 or n > 64 for n in sizes):
        raise ValueError(f"--robots must be a comma-separated list of sizes in 1..64, got {args.robots!r}")
    if not (0 < args.command_hz <= 1000):
        raise ValueError(f"--command-hz must be in (0, 1000], got {args.command_hz!r}")
    for inference in args.inference:  # the settings' own validation (inference = "ray" needs Ray installed)
        Settings(
            inference={"device": args.device, "backend": inference},
            workers={"robots_per_process": args.robots_per_process},
        )
    check_device(args.device)  # before any process starts
    before = None
    if args.compare:  # read before the run: a missing or unreadable file fails at once
        path = Path(args.compare)
        if not path.is_file():
            raise ValueError(f"--compare: no result file {args.compare!r}")
        before = json.loads(path.read_text())
    result = bench_fleet(
        args.task,
        sizes,
        args.seconds,
        progress=not args.quiet,
        torch_threads=args.torch_threads,
        command_hz=args.command_hz,
        workers=tuple(args.worker) if args.worker else None,
        robots_per_process=args.robots_per_process,
        device=args.device,
        inference=tuple(dict.fromkeys(args.inference)),
        policy=args.policy,
        signal=args.signal,
    )
    if before is not None:
        from bench.fleet import compare_with

        result["compare"] = compare_with(result, before)
    text = json.dumps(stamped(result), indent=None if args.json else 2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


def _cmd_bench_segments(args: argparse.Namespace) -> int:
    import json

    from bench.provenance import stamped
    from bench.segments import bench_segments

    if not 10 <= args.steps <= 100_000:
        raise ValueError(f"--steps must be in 10..100000, got {args.steps}")
    if not 0 <= args.control_hz <= 1000:
        raise ValueError(f"--control-hz must be in 0..1000, got {args.control_hz}")
    if args.dir is not None and not args.dir.is_dir():
        raise ValueError(f"--dir {args.dir} is not a folder")
    result = bench_segments(steps=args.steps, control_hz=args.control_hz, directory=args.dir, progress=not args.quiet)
    print(json.dumps(stamped(result), indent=None if args.json else 2))
    return 0


def _cmd_bench_api(args: argparse.Namespace) -> int:
    import json

    from bench.api import bench_api
    from bench.provenance import stamped

    if not 1 <= args.robots <= 64:
        raise ValueError(f"--robots must be in 1..64, got {args.robots}")
    if not 1 <= args.clients <= 1000:
        raise ValueError(f"--clients must be in 1..1000, got {args.clients}")
    if args.seconds <= 0 or args.idle_seconds <= 0:
        raise ValueError("--seconds and --idle-seconds must be positive")
    if not (0 < args.poll_hz <= 1000 and 0 < args.command_hz <= 1000):
        raise ValueError("--poll-hz and --command-hz must be in (0, 1000]")
    if not 0 <= args.api_workers <= 64:
        raise ValueError(f"--api-workers must be in 0..64, got {args.api_workers}")
    result = bench_api(
        robots=args.robots,
        clients=args.clients,
        seconds=args.seconds,
        idle_seconds=args.idle_seconds,
        task=args.task,
        worker=args.worker,
        control_hz=args.control_hz,
        poll_hz=args.poll_hz,
        command_hz=args.command_hz,
        api_workers=args.api_workers,
        progress=not args.quiet,
    )
    print(json.dumps(stamped(result), indent=None if args.json else 2))
    return 0


def _cmd_bench_loop(args: argparse.Namespace) -> int:
    import json

    from bench.loop import run_loop
    from bench.provenance import stamped

    if args.seconds <= 0:
        raise ValueError(f"--seconds must be positive, got {args.seconds}")
    env = _settings_env(args.set)
    result = run_loop(args.seconds, args.mode, args.config, args.data_dir, env, not args.no_bot, not args.quiet)
    print(json.dumps(stamped(result), indent=None if args.json else 2))
    return 0


def _cmd_bench_operators(args: argparse.Namespace) -> int:
    import json

    from bench.operators import OPERATORS_CONFIG, FleetMix, OperatorsPlan, Pace, run_operators
    from bench.provenance import stamped

    plan = OperatorsPlan(
        sizes=tuple(args.sizes),
        mix=FleetMix.parse(args.mix),
        ticks=args.ticks,
        control_hz=args.control_hz,
        pace=Pace(args.claim_ticks, args.switch_ticks, args.min_takeover_ticks),
        order=args.order,
        config=args.config or OPERATORS_CONFIG,
        overrides=_settings_env(args.set),
    )
    compare = []
    for item in args.compare or []:
        label, sep, path = item.partition("=")
        if not sep:
            raise ValueError(f"--compare takes LABEL=FILE, got {item!r}")
        compare.append((label, json.loads(Path(path).read_text())))
    if args.from_ is not None:  # an earlier run's report, drawn again (with --compare) and not rerun
        result = json.loads(args.from_.read_text())
    else:
        result = stamped(run_operators(plan, args.data_dir, not args.quiet))
    text = json.dumps(result, indent=None if args.json else 2)
    if args.out is not None and args.from_ is None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    if args.figure is not None:
        from bench.operators_figure import plot_operators

        plot_operators([(args.label, result), *compare], args.figure)
    print(text)
    return 0


def _settings_env(items: list[str] | None) -> dict[str, str]:
    """``--set KEY=VALUE`` items (``controller.budget=8``) as ``HITL_*`` variables for the service."""
    from server.settings import env_name, refuse_removed

    env = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not all(part.isidentifier() for part in key.split(".")):
            raise ValueError(f"--set takes KEY=VALUE with a settings key (section.key), got {item!r}")
        refuse_removed({key: value}, " in --set")
        env[env_name(key)] = value
    return env


def _cmd_bench_nights(args: argparse.Namespace) -> int:
    import json
    import sys
    import tempfile

    from bench.nights import NIGHTS_CONFIG, NightsPlan, run_nights
    from bench.nights_figure import plot_nights
    from bench.provenance import stamped

    data_dir = args.data_dir or Path(tempfile.mkdtemp(prefix="hitl-nights-"))
    config, days, minutes, episodes = args.config or NIGHTS_CONFIG, args.days, args.day_minutes, args.day_episodes
    if args.quick:
        from bench.nights_quick import quick_config, quick_policy

        if args.config is not None:
            raise ValueError("--quick makes its own tiny fleet: leave out --config")
        data_dir.mkdir(parents=True, exist_ok=True)
        config = quick_config(data_dir, quick_policy(data_dir / "quick"))
        days = args.days if args.days is not None else 2
        minutes = args.day_minutes if args.day_minutes is not None else 3.0
        episodes = args.day_episodes if args.day_episodes is not None else 2
    else:
        days = args.days if args.days is not None else 3
        if minutes is None and episodes is None:
            minutes = 12.0
    plan = NightsPlan(
        config=config,
        days=days,
        day_minutes=minutes,
        day_episodes=episodes,
        night_timeout_s=args.night_timeout * 60,
        data_dir=data_dir / "service" if args.quick else data_dir,
        env=_settings_env(args.set),
        progress=not args.quiet,
    )
    command = "hitl " + " ".join(sys.argv[1:])

    def write(report: dict) -> None:  # the report so far after every day and night, then the whole run's
        report |= {"quick": bool(args.quick), "command": command}
        stamped(report)
        if args.out:
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(report, indent=2) + "\n")

    result = run_nights(plan, on_progress=write)
    write(result)
    text = json.dumps(result, indent=None if args.json else 2)
    if args.figure:
        plot_nights(result, Path(args.figure))
    print(text)
    return 0


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    from server.auth import ROLES

    p = sub.add_parser("serve", help="run the fleet service (REST API, assistance queue, simulated fleet)")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--config", type=Path, default=None, help="TOML settings file (HITL_* variables override it)")
    p.add_argument(
        "--api-workers",
        type=int,
        default=None,
        help="serve the API and console from N processes of their own; the fleet runtime stays in this one "
        "(the settings' api_workers; 0: one process for all)",
    )
    p.add_argument(
        "--log-level",
        choices=["debug", "info", "warning"],
        default="info",
        help="debug adds the access-log lines of successful polling GETs (robots, queue, metrics, health)",
    )
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("operator-bot", help="simulated operator: claims queued robots and drives them via the API")
    p.add_argument("--url", required=True, help="service URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", required=True, help="an operator token")
    p.add_argument("--takeovers", type=int, default=None, help="stop after this many takeovers")
    p.add_argument(
        "--hand-back-when-held",
        action="store_true",
        help="release a robot once the object is held (default: drive until the service hands back)",
    )
    p.set_defaults(func=_cmd_operator_bot)

    q = bench.add_parser("finetune-load", help="the fleet's control rate while a fine-tuning job runs beside it")
    q.add_argument("--robots", type=int, default=8)
    q.add_argument("--task", default="lift-cube")
    q.add_argument("--control-hz", type=float, default=10.0)
    q.add_argument("--idle-seconds", type=float, default=20.0, help="measured before and after the job")
    q.add_argument("--seconds", type=float, default=60.0, help="measured while the job runs")
    q.add_argument("--niceness", type=int, default=19, help="the job's CPU priority (the setting)")
    q.add_argument("--no-idle-priority", action="store_true", help="nice only, without SCHED_IDLE (the setting)")
    q.add_argument("--out", default=None, help="also write the JSON here")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_finetune_load)

    q = bench.add_parser("fleet", help="fleet throughput against raw physics; command latency")
    q.add_argument("--robots", default="1,4,8,16")
    q.add_argument("--task", default="lift-cube")
    q.add_argument("--seconds", type=float, default=10.0)
    q.add_argument("--torch-threads", type=int, default=1, help="server-side torch threads (the setting)")
    q.add_argument("--command-hz", type=float, default=30.0, help="the bench operator's command stream rate")
    q.add_argument(
        "--worker",
        nargs="+",
        choices=["process", "pool", "ray"],
        default=None,
        help="worker back ends (default: process, pool and, where Ray is installed, ray; side by side in one run)",
    )
    q.add_argument("--robots-per-process", type=int, default=8, help="pool back end (the setting)")
    q.add_argument("--policy", type=Path, default=None, help="the policy folder the robots run (default: bundled)")
    q.add_argument("--signal", default=None, help="the asking signal (default: the fleet's)")
    q.add_argument(
        "--inference",
        nargs="+",
        choices=["local", "ray"],
        default=["local"],
        help="where the policy and the signals run (the setting): each back end is measured with each",
    )
    q.add_argument("--device", default="cpu", help="where the policy and the uncertainty run: cpu, cuda, cuda:N")
    q.add_argument(
        "--compare",
        default=None,
        help="the previous release's result of this benchmark (JSON): each figure both hold, before and now",
    )
    q.add_argument("--out", default=None, help="also write the JSON here (--compare is read first)")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_fleet)

    q = bench.add_parser(
        "segments", help="what making each takeover step durable costs: flush per second, per step, fsync"
    )
    q.add_argument("--steps", type=int, default=300)
    q.add_argument("--control-hz", type=float, default=10.0, help="steps per second (0: back to back)")
    q.add_argument("--dir", type=Path, default=None, help="where the files go (default: a temporary folder)")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_segments)

    q = bench.add_parser("api", help="the service under concurrent REST/WebSocket clients; control rate idle vs load")
    q.add_argument("--robots", type=int, default=16)
    q.add_argument("--clients", type=int, default=50, help="REST pollers, WebSocket streams and queue cyclers")
    q.add_argument("--seconds", type=float, default=30.0, help="measurement under load")
    q.add_argument("--idle-seconds", type=float, default=15.0, help="measurement of the idle fleet, before")
    q.add_argument("--task", default="lift-cube")
    q.add_argument("--worker", choices=["process", "in-process"], default="process")
    q.add_argument("--control-hz", type=float, default=10.0)
    q.add_argument("--poll-hz", type=float, default=5.0, help="requests per second of each REST poller")
    q.add_argument("--command-hz", type=float, default=30.0, help="commands per second of each WebSocket stream")
    q.add_argument(
        "--api-workers",
        type=int,
        default=0,
        help="0: the API in the fleet runtime's process; N: in N processes of its own (the service's api_workers)",
    )
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_api)

    q = bench.add_parser("loop", help="the demo fleet served with the operator bot helping: success per task")
    q.add_argument("--seconds", type=float, default=1200.0, help="wall-clock time after the service is ready")
    q.add_argument("--mode", choices=["budgeted", "continuous"], default="continuous", help="hand-back mode")
    q.add_argument("--config", type=Path, default=None, help="service config (default: configs/demo.toml)")
    q.add_argument("--data-dir", type=Path, default=None, help="where the run's database goes (default: a temp dir)")
    q.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="a setting, e.g. controller.cooldown=20 (none unsets an optional one)",
    )
    q.add_argument("--no-bot", action="store_true", help="no operator: what the fleet does on its own")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_loop)

    q = bench.add_parser(
        "operators",
        help="robots per operator: fleets of each size served by one simulated operator, through the service",
    )
    q.add_argument("--sizes", type=int, nargs="+", default=[8, 10, 15, 20], help="fleet sizes, each a fresh service")
    q.add_argument(
        "--mix", nargs="+", metavar="TASK=SHARE", help="default lift-cube=0.7 and 0.1 of hammer, cup, drawer"
    )
    q.add_argument("--ticks", type=int, default=3000, help="ticks of the fleet's clock each size runs")
    q.add_argument("--control-hz", type=float, default=None, help="the fleet's clock (default: the config's, 10 Hz)")
    q.add_argument("--order", choices=["priority", "cur", "fcfs"], default="priority", help="the queue's order")
    q.add_argument("--claim-ticks", type=int, default=10, help="the operator's delay to claim a request")
    q.add_argument("--switch-ticks", type=int, default=20, help="further delay when switching to another robot")
    q.add_argument("--min-takeover-ticks", type=int, default=20, help="the least time a takeover occupies them")
    q.add_argument("--config", type=Path, default=None, help="service config (default: configs/operators.toml)")
    q.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="a setting, e.g. controller.signal=denoising (none unsets an optional one)",
    )
    q.add_argument("--data-dir", type=Path, default=None, help="where each size's service folder goes (default: temp)")
    q.add_argument("--out", type=Path, default=None, help="also write the JSON report here")
    q.add_argument("--figure", type=Path, default=None, help="success and queue wait against the fleet's size")
    q.add_argument("--label", default="today", help="this run's label in the figure")
    q.add_argument("--compare", nargs="+", metavar="LABEL=FILE", help="earlier reports drawn beside it")
    q.add_argument(
        "--from", dest="from_", type=Path, default=None, help="draw this earlier report (--figure) instead of running"
    )
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_operators)

    q = bench.add_parser(
        "nights", help="days of the fleet with an operator, nights of fine-tuning by the service's scheduler"
    )
    q.add_argument("--config", type=Path, default=None, help="service config (default: configs/nights.toml)")
    q.add_argument("--days", type=int, default=None, help="days, with a night between each two (default 3; --quick 2)")
    q.add_argument("--day-minutes", type=float, default=None, help="a day's length (default 12 without --day-episodes)")
    q.add_argument("--day-episodes", type=int, default=None, help="or: a day ends once each task finished this many")
    q.add_argument(
        "--night-timeout", type=float, default=180.0, help="minutes a night's job may take before the run stops"
    )
    q.add_argument("--data-dir", type=Path, default=None, help="the run's service folder (default: a temp dir)")
    q.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="a setting, e.g. controller.cooldown=20 (none unsets an optional one)",
    )
    q.add_argument("--quick", action="store_true", help="a tiny fleet and job, for CI (2 days, minutes)")
    q.add_argument("--out", type=Path, default=None, help="also write the JSON report here")
    q.add_argument("--figure", type=Path, default=None, help="write the effort-and-success figure here (PNG)")
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_nights)

    p = sub.add_parser("token", help="create or revoke API tokens")
    p.add_argument("action", choices=["create", "revoke"])
    p.add_argument("--name", required=True)
    p.add_argument("--role", choices=ROLES, default="viewer")
    p.add_argument("--config", type=Path, default=None)
    p.set_defaults(func=_cmd_token)

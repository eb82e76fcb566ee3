"""``hitl docs screenshots`` and ``hitl bench console``: the operator console's pictures and its cost."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path


def _cmd_screenshots(args: argparse.Namespace) -> int:
    from bench.screenshots import take_screenshots

    for path in take_screenshots(args.config, args.out, chromium=args.chromium):
        print(f"wrote {path}")
    return 0


def _cmd_bench_console(args: argparse.Namespace) -> int:
    from bench.console import bench_console
    from bench.provenance import stamped

    if not 1 <= args.browsers <= args.robots <= 64:
        raise ValueError(f"need 1 <= --browsers <= --robots <= 64, got {args.browsers} and {args.robots}")
    if args.seconds <= 0 or args.idle_seconds <= 0:
        raise ValueError("--seconds and --idle-seconds must be positive")
    result = bench_console(
        robots=args.robots,
        browsers=args.browsers,
        seconds=args.seconds,
        idle_seconds=args.idle_seconds,
        control_hz=args.control_hz,
        nice=args.nice,
        paint=not args.no_paint,
        clients=args.clients,
        cameras=not args.no_cameras,
        chromium=args.chromium,
        progress=not args.quiet,
    )
    result["command"] = "hitl " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    stamped(result)
    text = json.dumps(result, indent=None if args.json else 2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["met"] else 1


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    docs = sub.add_parser("docs", help="generate documentation assets").add_subparsers(dest="docs", required=True)
    p = docs.add_parser(
        "screenshots", help="the console in headless Chromium on the demo fleet: docs/figures/console-*.png"
    )
    p.add_argument("--config", type=Path, default=Path("configs/demo.toml"))
    p.add_argument("--out", type=Path, default=Path("docs/figures"))
    p.add_argument("--chromium", default="/usr/bin/chromium")
    p.set_defaults(func=_cmd_screenshots)

    q = bench.add_parser("console", help="the console's cost: fleet env steps/s with and without browsers open")
    q.add_argument("--robots", type=int, default=16)
    q.add_argument("--browsers", type=int, default=4, help="Chromium pages, each viewing its own robot")
    q.add_argument("--seconds", type=float, default=30.0)
    q.add_argument("--idle-seconds", type=float, default=20.0)
    q.add_argument("--control-hz", type=float, default=10.0)
    q.add_argument("--nice", type=int, default=19, help="the browsers' niceness (they share this machine)")
    q.add_argument(
        "--no-paint", action="store_true", help="the pages take every update but do not paint the 3D view (software GL)"
    )
    q.add_argument(
        "--clients",
        choices=["chromium", "wire"],
        default="chromium",
        help="chromium: real browsers on this machine; wire: viser protocol clients, no browser (the service's cost)",
    )
    q.add_argument(
        "--no-cameras", action="store_true", help="no camera views (the viewed robots' front and wrist cameras)"
    )
    q.add_argument("--chromium", default="/usr/bin/chromium")
    q.add_argument(
        "--out", type=Path, default=None, help="also write the JSON here (e.g. docs/results/console/chromium.json)"
    )
    q.add_argument("--json", action="store_true")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=_cmd_bench_console)

"""What several ``hitl`` subcommands share: argument types, the uncertainty flags, torch's thread
count, loading a policy with its calibration, and opening the service's database."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_BAD_INPUT = 2

UNCERTAINTY_ARGS = {  # flag -> UncertaintyConfig field; the defaults live in UncertaintyConfig only
    "samples": "num_samples",
    "radius": "radius",
    "max_modes": "max_modes",
    "criterion": "criterion",
    "alpha": "alpha",
    "backend": "backend",
}


def uncertainty_config(args: argparse.Namespace):
    from policy.uncertainty import UncertaintyConfig

    given = {f: getattr(args, a) for a, f in UNCERTAINTY_ARGS.items() if getattr(args, a) is not None}
    return UncertaintyConfig(**given)


def add_uncertainty_args(p: argparse.ArgumentParser) -> None:
    from policy.gmm import BACKENDS, CRITERIA
    from policy.uncertainty import UncertaintyConfig

    d = UncertaintyConfig()
    p.add_argument("--samples", type=int, help=f"probe samples S per robot (default {d.num_samples})")
    p.add_argument("--radius", type=float, help=f"probe radius r, normalized action space (default {d.radius})")
    p.add_argument("--max-modes", type=int, help=f"default {d.max_modes}")
    p.add_argument("--criterion", choices=list(CRITERIA), help=f"default {d.criterion}")
    p.add_argument("--alpha", type=float, help=f"default {d.alpha}")
    p.add_argument("--backend", choices=list(BACKENDS), help=f"default {d.backend}")


def int_at_least(low: int):
    """An argparse type: an integer >= low, with a clear message otherwise."""

    def parse(text: str) -> int:
        value = int(text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse names the type in "invalid integer value: ..."
    return parse


non_negative_int, positive_int = int_at_least(0), int_at_least(1)


def set_threads(args: argparse.Namespace) -> None:
    if getattr(args, "threads", None):
        import torch

        torch.set_num_threads(args.threads)


def policy_with(args: argparse.Namespace):
    """Loads the policy (optionally with another DDIM step count) and its calibration; CheckpointError
    (exit 2) when it cannot run the task it is run on (``--task``, else the one it was trained on:
    ``policy.checkpoint.check_fits``)."""
    from dataclasses import replace

    from policy.checkpoint import check_fits, load_calibration, load_policy
    from policy.diffusion_policy import DiffusionPolicy

    policy, info = load_policy(args.policy)
    if task := getattr(args, "task", None) or info.get("task"):
        check_fits(info, task, args.policy)
    if getattr(args, "ddim_steps", None):
        state = policy.state_dict()
        policy = DiffusionPolicy(replace(policy.config, num_inference_steps=args.ddim_steps))
        policy.load_state_dict(state)
        policy.eval()
    return policy, info, load_calibration(args.policy)


def add_store_args(p: argparse.ArgumentParser) -> None:
    """--config, --data-dir, --database-url: where the service keeps its data and database."""
    p.add_argument("--config", type=Path, default=None, help="the service's TOML settings (data_dir, database)")
    p.add_argument("--data-dir", type=Path, default=None, help="the service's data folder (default: settings)")
    p.add_argument("--database-url", default=None, help="default: settings, DATABASE_URL or data_dir/hitl.db")


def open_store(args: argparse.Namespace):
    """(settings, sessions) with the migrations applied."""
    from server.db import make_engine, migrate, session_factory
    from server.settings import Settings

    overrides = {}
    if getattr(args, "data_dir", None):
        overrides["data_dir"] = args.data_dir
    if getattr(args, "database_url", None):
        overrides["database_url"] = args.database_url
    settings = Settings.load(args.config, **overrides)
    migrate(settings.db_url)
    return settings, session_factory(make_engine(settings.db_url))


def fail(command: str, exc: Exception) -> int:
    """Prints ``hitl COMMAND: error: ...`` to stderr; returns EXIT_BAD_INPUT."""
    print(f"hitl {command}: error: {getattr(exc, 'message', exc)}", file=sys.stderr)
    return EXIT_BAD_INPUT

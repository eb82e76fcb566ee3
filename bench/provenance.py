"""What made a result: the command line, the commit and the date, recorded in the result itself under
``"provenance"``, so that every figure the docs quote names the run it came from."""

from __future__ import annotations

import datetime
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def provenance(argv: list[str] | None = None) -> dict:
    """``command``: ``hitl`` and ``argv`` (this process's arguments by default); ``commit``: the code's
    ``git rev-parse HEAD`` (``"unknown"`` outside a git checkout), with ``uncommitted_changes`` where its
    tracked files differ from that commit; ``date``: now, UTC, ISO 8601."""
    args = sys.argv[1:] if argv is None else argv
    commit = _git("rev-parse", "HEAD") or "unknown"
    out = {"command": "hitl " + shlex.join(args), "commit": commit}
    if commit != "unknown" and _git("status", "--porcelain", "--untracked-files=no"):
        out["uncommitted_changes"] = True
    out["date"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    return out


def stamped(result: dict, argv: list[str] | None = None) -> dict:
    """``result`` with its ``provenance`` set (keys it already holds, such as seeds, kept)."""
    result["provenance"] = {**result.get("provenance", {}), **provenance(argv)}
    return result

"""Process CPU time and memory from Linux ``/proc``, for the benchmarks (empty or None elsewhere)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

TICKS_PER_SECOND = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_ticks(pids: dict[str, int]) -> dict[str, int]:
    """CPU clock ticks: the machine's busy time (``machine``), and each named process's user + system."""
    out = {}
    with contextlib.suppress(OSError, ValueError, IndexError):
        v = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        out["machine"] = sum(v) - v[3] - v[4]  # all but idle and iowait
    for name, pid in pids.items():
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            out[name] = int(fields[11]) + int(fields[12])  # utime + stime
    return out


def processes_cpu_seconds(pids: dict[str, int]) -> float:
    """User + system CPU seconds of the named processes together (not the machine's busy time)."""
    ticks = cpu_ticks(pids)
    return sum(ticks.get(name, 0) for name in pids) / TICKS_PER_SECOND


def memory_mb(pid: int | str = "self") -> dict:
    """Resident (``rss_mb``) and peak resident (``peak_rss_mb``) memory of a process, in MB."""
    out = {"rss_mb": None, "peak_rss_mb": None}
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out["rss_mb" if key == "VmRSS" else "peak_rss_mb"] = int(value.split()[0]) / 1024
    return out


def worker_pids(robots) -> dict[str, int]:
    """The processes the robots' physics run in, once each (robots sharing a pooled process share it)."""
    pids = {getattr(r.worker, "pid", None) for r in robots if r.worker is not None}
    return {f"worker{pid}": pid for pid in sorted(p for p in pids if p)}


def descendant_pids(root: int | None = None) -> dict[str, int]:
    """Every live process descended from ``root`` (default: this one), by ``/proc``'s parent links:
    with ``worker_pids`` removed, the back end's own processes (a local Ray instance's raylet and
    GCS, say)."""
    root = os.getpid() if root is None else root
    parents: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, ValueError, IndexError):
                parents[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
    found, frontier = set(), {root}
    while frontier:
        frontier = {pid for pid, parent in parents.items() if parent in frontier and pid not in found}
        found |= frontier
    return {f"child{pid}": pid for pid in sorted(found)}

"""``hitl bench segments``: what it costs to make each takeover step durable.

A takeover's steps are written by ``storage.segments.SegmentWriter`` into a chunked MCAP file. A step
is safe from a crash of the server once its chunk has been handed to the operating system (a
``flush``), and from a crash of the machine once the disk has it (``fsync``). This benchmark writes the
same takeover steps as the fleet does (an observation, the command, the absolute and normalized
action, the pose, the scores and the denoising field of ``--field-samples`` arrows) under each policy:

- ``interval``: a flush at most once a second (what the service did before): a crash of the server
  loses up to a second of steps;
- ``step``: a flush after every step, before the next tick: a crash of the server loses none;
- ``step+fsync``: also an fsync after every step: a crash of the machine loses none.

It reports the time per step (the write, compression and the flush: what the control loop spends),
the file's bytes per step, and what a crash loses. The files go to ``--dir`` (default: a temporary
folder on the data root's disk), since an fsync costs what that disk costs.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.harness import dist
from storage.segments import SegmentWriter

MODES = {"interval": (1.0, False), "step": (0.0, False), "step+fsync": (0.0, True)}
LOSES = {
    "interval": "up to 1 s of steps on a crash of the server",
    "step": "no step on a crash of the server; what the OS had not written on a crash of the machine",
    "step+fsync": "no step on a crash of the server or of the machine",
}


def _steps(n: int, obs_dim: int, field_samples: int, seed: int) -> list[tuple]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        action = rng.normal(size=10)
        field = (rng.normal(size=(field_samples, 3)), rng.normal(size=(field_samples, 3)) * 1e-3,
                 rng.integers(0, 3, field_samples), 0.02)  # fmt: skip
        command = {"delta_pos": [0.01, 0.0, 0.0], "delta_rot": [0.0, 0.0, 0.0], "gripper": 1.0, "clamped": [False]}
        out.append((rng.normal(size=obs_dim), command, action, action / 2, action[:3], [0, 0, 0, 1.0], 0.5, field))
    return out


def write_segment(path: Path, steps: list[tuple], mode: str, period_s: float) -> list[float]:
    """Seconds per ``write_step`` (with its flush) of ``steps`` at one step per ``period_s``."""
    flush_seconds, fsync = MODES[mode]
    writer = SegmentWriter(path, {"robot": 0, "operator": "bench"}, flush_seconds, fsync)
    times = []
    try:
        for obs, cmd, act, label, pos, quat, u, field in steps:
            t0 = time.perf_counter()
            writer.write_step(obs, cmd, act, label, pos, quat, u, shadow={"choice-stall": 1.0}, field=field)
            times.append(time.perf_counter() - t0)
            time.sleep(period_s)  # the control period: an interval flush happens once a second, as served
    finally:
        writer.close("closed", "hand-back")
    return times


def bench_segments(
    steps: int = 300,
    obs_dim: int = 40,
    field_samples: int = 128,
    control_hz: float = 10.0,
    directory: Path | None = None,
    progress: bool = True,
) -> dict:
    data = _steps(steps, obs_dim, field_samples, seed=0)
    period = 1.0 / control_hz if control_hz > 0 else 0.0
    rows = {}
    with tempfile.TemporaryDirectory(prefix="hitl-bench-segments-", dir=directory) as tmp:
        write_segment(Path(tmp) / "warm-up.mcap", data[:30], "step", 0.0)  # imports, caches, CPU clock up
        for mode in tqdm(MODES, desc="bench segments", disable=not progress):
            path = Path(tmp) / f"{mode.replace('+', '-')}.mcap"
            times = write_segment(path, data, mode, period)
            rows[mode] = {
                "per_step": {**dist(times), "mean_ms": float(np.mean(times) * 1e3)},
                "bytes_per_step": path.stat().st_size / steps,
                "a_crash_loses": LOSES[mode],
            }
    base = rows["interval"]["per_step"]["mean_ms"]
    for row in rows.values():
        row["extra_ms_per_step"] = row["per_step"]["mean_ms"] - base
    return {
        "benchmark": "segments",
        "config": {"steps": steps, "obs_dim": obs_dim, "field_samples": field_samples, "control_hz": control_hz},
        "directory": "the system's temporary folder" if directory is None else str(directory),
        "modes": rows,
    }

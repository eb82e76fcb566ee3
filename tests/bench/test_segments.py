"""``hitl bench segments``: every flush policy writes the same steps into a readable takeover file."""

import json
import subprocess
import sys

from bench.segments import MODES, bench_segments
from storage.segments import read_segment


def test_every_flush_policy_is_timed_on_the_same_steps(tmp_path):
    out = bench_segments(steps=12, control_hz=0, directory=tmp_path, progress=False)
    assert set(out["modes"]) == set(MODES) and out["directory"] == str(tmp_path)
    for row in out["modes"].values():
        assert row["per_step"]["count"] == 12 and row["per_step"]["mean_ms"] > 0
        assert row["bytes_per_step"] > 1000  # the field's arrows are most of a step
    assert out["modes"]["interval"]["extra_ms_per_step"] == 0.0
    assert not list(tmp_path.iterdir())  # its files go with its temporary folder


def test_the_files_it_writes_are_complete_takeovers(tmp_path):
    from bench.segments import _steps, write_segment

    path = tmp_path / "s.mcap"
    write_segment(path, _steps(5, 40, 16, seed=1), "step+fsync", 0.0)
    segment = read_segment(path)
    assert len(segment.steps) == 5 and segment.end["ended_by"] == "hand-back"


def test_the_command_refuses_a_folder_that_does_not_exist(tmp_path):
    cmd = [sys.executable, "-m", "hitl.cli", "bench", "segments", "--dir", str(tmp_path / "nope"), "--json"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "is not a folder" in run.stderr
    assert not run.stdout.strip() or "modes" not in json.loads(run.stdout or "{}")

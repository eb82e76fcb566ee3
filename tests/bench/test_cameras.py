"""``hitl bench cameras``: both drawings timed on an expert's steps, and the figure of what the policy sees."""

import json

import pytest

from bench.cameras import CameraBench
from hitl.cli import main


def test_the_bench_times_both_drawings_and_draws_the_policys_views(tmp_path, capsys):
    out, figure = tmp_path / "cameras.json", tmp_path / "cameras.png"
    args = ["bench", "cameras", "--tasks", "open-drawer", "--steps", "3", "--figure", str(figure), "--out", str(out)]
    assert main([*args, "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert json.loads(capsys.readouterr().out) == result
    [row] = result["tasks"]
    assert row["task"] == "open-drawer" and row["steps"] == 3 and row["cameras"][0]["name"] == "side"
    assert row["default_ms_per_step"] > 0 and row["served_ms_per_step"] > 0
    assert {"command", "commit", "date"} <= set(result["provenance"]) and figure.stat().st_size > 1000


def test_a_bad_plan_is_refused():
    with pytest.raises(KeyError, match="unknown task"):
        CameraBench(tasks=("lift-banana",))
    with pytest.raises(ValueError, match="steps"):
        CameraBench(steps=0)

import json
from pathlib import Path

import pytest

from bench.hitl.docs import markdown
from bench.hitl.report import fewest_steps, summarize
from bench.hitl.run import BenchError, Cache, Cell, Recipe, SignalSpec, run_chains
from hitl.cli import main
from tests.helpers import tiny_policy_folder


def test_signal_specs_parse_variants_and_name_them():
    spec = SignalSpec.parse("denoising:radius=0.01,criterion=likelihood")
    assert spec.name == "denoising" and dict(spec.settings) == {"radius": 0.01, "criterion": "likelihood"}
    assert spec.label == "denoising[radius=0.01,criterion=likelihood]"
    assert SignalSpec.parse("thrifty").label == "thrifty"
    with pytest.raises(BenchError, match="key=value"):
        SignalSpec.parse("denoising:radius")


def test_recipes_reject_what_cannot_run():
    policies = (("lift-hammer", "p"),)
    with pytest.raises(BenchError, match="episodes"):
        Recipe(policies, ("lift-hammer",), (SignalSpec("random"),), episodes=0, false_alarm_task=None)
    with pytest.raises(BenchError, match="quantiles"):
        Recipe(policies, ("lift-hammer",), (SignalSpec("random"),), quantiles=(1.5,), false_alarm_task=None)
    with pytest.raises(BenchError, match="no policy"):
        Recipe(policies, ("lift-hammer",), (SignalSpec("random"),))  # lift-cube's false alarms need one


def _point(label, success, steps):
    return {"label": label, "success_rate": success, "assisted_steps": steps}


def test_the_fewest_steps_are_taken_among_points_that_reach_the_target():
    curve = [_point("a", 1.0, 30.0), _point("b", 0.95, 12.0), _point("c", 1.0, 20.0), _point("d", 0.5, 2.0)]
    assert fewest_steps(curve, 1.0)["label"] == "c"
    assert fewest_steps(curve, 0.95)["label"] == "b"
    assert fewest_steps([_point("d", 0.5, 2.0)], 1.0) is None


def _cell(label):
    return Cell("assist", "t", "p", (1,), 4, 1, spec=SignalSpec("x"), threshold=0.0, label=label, key=label)


def _fake_work(cell):  # cell "q2" brings every episode to success
    return {"episodes": [{"success": cell.label == "q2"}]}


def test_a_sweep_stops_at_full_success_and_reruns_come_from_the_cache(tmp_path):
    cache = Cache(tmp_path)
    chain = [_cell("q1"), _cell("q2"), _cell("q3")]
    ran = []

    def work(cell):
        ran.append(cell.label)
        return _fake_work(cell)

    stop = lambda r: all(e["success"] for e in r["episodes"])  # noqa: E731
    out = run_chains([chain, [_cell("solo")]], cache, progress=False, stop=stop, work=work)
    assert ran == ["q1", "q2", "solo"] and set(out) == {"q1", "q2", "solo"}
    ran.clear()
    again = run_chains([chain], cache, progress=False, stop=stop, work=work)
    assert ran == [] and again["q2"] == out["q2"]


def test_summaries_report_curves_defaults_and_unreached_targets():
    def entry(signal, label, successes, steps):
        eps = [{"success": s, "assisted_steps": steps, "events": 1, "steps": 50} for s in successes]
        return {"task": "t", "signal": signal, "label": label, "result": {"threshold": 0.1, "episodes": eps}}

    raw = {
        "recipe": {"tasks": ["t"], "policies": {"t": "p"}, "false_alarm_task": None},
        "recipe_hash": "h",
        "reference": {},
        "shadow": {},
        "assisted": [
            entry("a", "reference", [True, False], 5),
            entry("a", "q0.9", [True, True], 9),
            entry("a", "q0.5", [True, True], 30),
            entry("b", "q0.9", [False, False], 1),
            {"task": "t", "signal": "a", "label": "q0.25", "result": None},  # not needed by the sweep
        ],
    }
    s = summarize(raw)["tasks"]["t"]["signals"]
    assert s["a"]["best_100"]["assisted_steps"] == 9 and s["a"]["default"]["success_rate"] == 0.5
    assert [p["label"] for p in s["a"]["curve"]] == ["q0.9", "q0.5"]
    assert s["b"]["best_100"] is None and s["b"]["best_95"] is None
    # the main section puts the paper's table beside ours; an ablation section lists every point instead
    main_text = markdown(summarize(raw), [], Path("report.md"))
    ablation = markdown(summarize(raw), [], Path("report.md"), paper=False)
    assert "The paper's table" in main_text and "Every threshold" not in main_text
    assert "The paper's table" not in ablation
    assert "| a | q0.9: 100% / 9.0<br>q0.5: 100% / 30.0 |" in ablation


def test_bench_hitl_quick_runs_a_tiny_configuration_through_the_controller(tmp_path, capsys):
    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1e9)  # its own calibration never asks
    argv = ["bench", "hitl", "--quick", "--tasks", "lift-hammer", "--policy", f"lift-hammer={folder}"]
    argv += [f"lift-cube={folder}", "--signals", "denoising", "random", "full-teleop", "--episodes", "2"]
    argv += ["--reference-episodes", "1", "--quantiles", "0.5", "--jobs", "1", "--cache", str(tmp_path / "cache")]
    argv += ["--report", str(tmp_path / "bench.md"), "--figures", str(tmp_path / "img"), "--json", "--quiet"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    row = out["tasks"]["lift-hammer"]["signals"]
    full = row["full-teleop"]["default"]
    # the scripted operator, in 4-step takeovers from the operator view, lifts the hammer every time
    assert full["success_rate"] == 1.0 and full["assisted_steps"] > 20
    assert row["full-teleop"]["best_100"] == full
    # a threshold that never asks never gets help and replays the policy's shadow run exactly
    never = row["denoising"]["default"]
    assert never["assisted_steps"] == 0 and never["success_rate"] == out["tasks"]["lift-hammer"]["autonomous_success"]
    assert row["random"]["curve"][0]["help_rate"] > 0.2  # random at rate 1 - 0.5
    auroc = out["diagnostics"]["tasks"]["lift-hammer"]["auroc"]["denoising"]
    alone = out["tasks"]["lift-hammer"]["autonomous_success"]
    # defined when the untrained policy's episodes include both an autonomous success and a failure
    assert (0.0 <= auroc <= 1.0) if 0.0 < alone < 1.0 else auroc is None
    assert out["false_alarms"]["task"] == "lift-cube"
    text = (tmp_path / "bench.md").read_text()
    assert "| full-teleop |" in text and "hitl bench hitl" in text
    assert (tmp_path / "img" / "hitl-curve-lift-hammer.png").is_file()
    assert (tmp_path / "img" / "hitl-timeline-lift-hammer.png").is_file()
    # a rerun reads every cell back from the cache and reports the same numbers
    files = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert main(argv) == 0
    again = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == files
    assert again["tasks"] == out["tasks"] and again["diagnostics"] == out["diagnostics"]
    # --cached-only reports a run in progress without running anything: here, nothing is missing
    assert main([*argv, "--cached-only"]) == 0
    cached = json.loads(capsys.readouterr().out)
    assert cached["tasks"] == out["tasks"] and cached["pending_cells"] == 0


def test_cached_only_reports_what_has_not_run_yet(tmp_path, capsys):
    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1e9)
    argv = ["bench", "hitl", "--tasks", "lift-hammer", "--policy", f"lift-hammer={folder}", f"lift-cube={folder}"]
    argv += ["--signals", "random", "--episodes", "1", "--reference-episodes", "1", "--quantiles", "0.5"]
    argv += ["--cache", str(tmp_path / "cache"), "--cached-only", "--json", "--quiet"]
    assert main(argv) == 2  # nothing has run: the sweep's thresholds are not known yet
    assert "reference rollouts" in capsys.readouterr().err


def _shadow_raw(floor_first: int | None = 3):
    """Two shadow episodes of task t: seed 1 fails alone (its score rises at steps 3-6), seed 2 succeeds."""
    fail = {"seed": 1, "success": False, "steps": 10, "scores": {"s": [0, 0, 0, 5, 5, 5, 5, 0, 0, 9]}, "wants": {}}
    ok = {"seed": 2, "success": True, "steps": 10, "scores": {"s": [1] * 10}, "wants": {"s": [0] * 9 + [1]}}
    raw = {
        "recipe": {"tasks": ["t"], "policies": {"t": "p"}, "false_alarm_task": "t", "budget": 4},
        "recipe_hash": "h",
        "reference": {},
        "shadow": {"t": {"episodes": [fail, ok]}},
        "assisted": [],
    }
    episodes = [
        {"seed": 1, "success": True, "first_request": floor_first},
        {"seed": 2, "success": True, "first_request": None},
    ]
    floor = {"tasks": {"t": {"floor": {"eval": {}, "episodes": episodes}, "best": None}}}
    return raw, floor


def test_the_floor_label_marks_the_states_where_the_oracles_help_rescued_an_episode():
    raw, floor = _shadow_raw()
    diag = summarize(raw, floor)["diagnostics"]["tasks"]["t"]
    # the late label takes the failure's last 10 steps, among them the final 9: above every negative but not all
    assert diag["auroc"]["s"] < 1.0
    # the floor label takes steps 3..6 (4 operator steps from the oracle's first request): all above the negatives
    assert diag["floor_positives"] == 4 and diag["floor_episodes"] == 1 and diag["auroc_floor"]["s"] == 1.0
    raw, floor = _shadow_raw(floor_first=0)  # the oracle asked at the start: steps 0..3, one of them above
    assert summarize(raw, floor)["diagnostics"]["tasks"]["t"]["auroc_floor"]["s"] == 0.25
    assert "auroc_floor" not in summarize(raw)["diagnostics"]["tasks"]["t"]  # no floor given: the late label only


def test_false_alarms_count_the_episodes_that_ask_at_all():
    raw, _ = _shadow_raw()
    fa = summarize(raw)["false_alarms"]["signals"]["s"]
    assert fa["episodes_asking"] == 1.0 and fa["default"] == pytest.approx(0.1)  # one step of ten, in its one episode


def test_the_headline_sets_the_paper_the_floor_the_shipped_signal_and_the_best_sweeps_side_by_side():
    from bench.hitl.headline import markdown as headline

    def pt(label, success, steps, events):
        return {"label": label, "success_rate": success, "assisted_steps": steps, "events": events}

    def row(default, curve=()):
        r = {"default": default, "curve": list(curve), "skipped": None, "pending": 0}
        pts = r["curve"] + ([default] if default else [])
        r["best_100"] = min((p for p in pts if p["success_rate"] >= 1), key=lambda p: p["assisted_steps"], default=None)
        return r

    summary = {
        "tasks": {
            "open-drawer": {
                "signals": {
                    "full-teleop": row(pt("reference", 1.0, 100.0, 25.0)),
                    "mine": row(pt("reference", 1.0, 4.0, 1.0), [pt("q0.5", 1.0, 2.0, 0.5)]),
                    "denoising": row(pt("reference", 0.5, 10.0, 3.0), [pt("q0.5", 0.9, 40.0, 10.0)]),
                    "other": row(pt("reference", 0.5, 10.0, 3.0)) | {"pending": 2},
                }
            }
        },
        "provenance": {"seeds": [1000, 1019], "command": "hitl bench hitl"},
    }
    floor = {
        "tasks": {
            "open-drawer": {"floor": None, "best": {"eval": {"success_rate": 0.95, "ratio": 0.04, "requests": 1.0}}}
        }
    }
    text = headline(summary, floor, "mine")
    assert "| paper, its metric (Table I) | 0.07 |" in text
    assert "| paper, its best baseline | 0.14 (`diff-dagger`) |" in text
    assert "| **floor** (oracle, best of its sweep) | — (95%: 0.04, 1.0) |" in text
    assert "| **`mine`, the fleet's signal, as shipped** | 0.04, 1.0 |" in text  # its own calibration, not its sweep
    assert "| `denoising`, the paper's metric, best of its sweep | — (90%: 0.40) |" in text
    assert "| `mine`, best of its sweep | 0.02, 0.5 |" in text
    assert "| `other`, best of its sweep | pending — (50%: 0.10) |" in text  # its sweep has cells to run
    assert "pending:" not in text  # the run had none left (summary["pending_cells"])
    assert text.index("`denoising`") < text.index("`mine`, best")

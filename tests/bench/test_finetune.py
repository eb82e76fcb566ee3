"""``hitl bench finetune``'s data handling and verdict (the rollouts themselves run in the benchmark)."""

from types import SimpleNamespace

import numpy as np
import pytest

from bench.finetune.report import markdown, summarize
from bench.finetune.run import (
    FULL,
    GRASP,
    GRASP_WINDOW,
    FinetuneBenchConfig,
    Samples,
    first_close_summary,
    grasp_window,
)
from policy.finetune import FinetuneConfig
from storage.takeovers import TakeoverSelection


def _run(start: int, n: int, close_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """n steps whose observation is its step number (start, start + 1, ...); the gripper closes from close_at."""
    obs = np.arange(start, start + n, dtype=np.float32)[:, None].repeat(3, 1)
    act = np.zeros((n, 10), np.float32)
    act[:, -1] = -1.0
    if close_at is not None:
        act[close_at:, -1] = 1.0
    return obs, act


def test_the_first_k_samples_are_whole_runs_in_order_spread_over_the_tasks(tmp_path):
    samples = Samples({"a": [_run(0, 4), _run(100, 5)], "b": [_run(200, 3), _run(300, 9)]})
    path = tmp_path / "s.npz"
    samples.save(path)
    samples = Samples.load(path)
    assert samples.count() == {"a": 9, "b": 12}

    got = samples.draw(13)[0]  # 7 from a (the first one: 13 % 2), 6 from b
    assert got.obs[:, 0].tolist() == [0, 1, 2, 3, 100, 101, 102, 200, 201, 202, 300, 301, 302]
    assert got.episode_ends.tolist() == [4, 7, 10, 13]  # the last run of each task is cut, never joined
    with pytest.raises(ValueError, match="only 9 samples of a collected, 10 wanted"):
        samples.draw(20)

    got = samples.draw(7, stride=2)[0]  # every other step of each run: a 0 2 | 100 102, b 200 202 | 300
    assert got.obs[:, 0].tolist() == [0, 2, 100, 102, 200, 202, 300]
    assert got.episode_ends.tolist() == [2, 4, 6, 7]


def test_a_selection_passes_over_failed_episodes_takeovers_and_keeps_the_last_steps_of_the_rest(tmp_path):
    samples = Samples({"a": [_run(0, 4), _run(100, 5), _run(200, 6)]}, {"a": [True, False, True]})
    path = tmp_path / "s.npz"
    samples.save(path)
    samples = Samples.load(path)
    assert samples.successful == {"a": [True, False, True]}

    keep = TakeoverSelection(successful_only=True, tail=3)
    got, recorded = samples.draw(5, selection=keep)
    # the last 3 steps of the first takeover; the failed episode's passed over; the third one cut to its last 2
    assert got.obs[:, 0].tolist() == [1, 2, 3, 204, 205] and got.episode_ends.tolist() == [3, 5]
    assert recorded == 4 + 5 + 6  # every takeover drawn from or passed over, whole
    assert samples.draw(5)[0].obs[:, 0].tolist() == [0, 1, 2, 3, 100]  # no selection: as recorded
    assert samples.draw(5)[1] == 4 + 5
    with pytest.raises(ValueError, match="only 6 samples of a collected, 7 wanted"):
        samples.draw(7, selection=keep)
    # demonstrations (no outcome recorded) are all kept
    assert Samples({"a": [_run(0, 4)]}).draw(2, selection=keep)[0].obs[:, 0].tolist() == [2, 3]
    # a cached collection serves another selection only if that one keeps enough of it
    assert samples.enough(6, keep) and not samples.enough(7, keep) and samples.enough(15, TakeoverSelection())


def test_a_repeat_draws_the_same_runs_in_another_seeded_order():
    samples = Samples({"a": [_run(i * 100, 3) for i in range(6)]}, {"a": [True, False, True, True, False, True]})
    assert samples.shuffled(0) is samples
    again = samples.shuffled(2)
    assert again.shuffled(0) is again and samples.shuffled(2).runs["a"][0][0][0, 0] == again.runs["a"][0][0][0, 0]
    starts = [int(o[0, 0]) for o, _ in again.runs["a"]]
    assert sorted(starts) == [0, 100, 200, 300, 400, 500] and starts != [0, 100, 200, 300, 400, 500]
    # each run keeps its episode's outcome
    assert again.successful["a"] == [s not in (100, 400) for s in starts]


def test_the_summary_averages_the_repeats_and_the_report_shows_each(tmp_path):
    result = {
        "config": {
            "train_task": "cube",
            "unseen": ["x", "y"],
            "sources": ["takeover:stall", FULL],
            "eval_episodes": 10,
            "eval_seed": 1,
            "hand_back": "operator",
            "cooldown": 10,
            "repeats": 2,
        },
        "pretrained": {"cube": {"success_rate": 1.0}, "x": {"success_rate": 0.0}, "y": {"success_rate": 0.0}},
        "points": [
            _point("takeover:stall", 100, (5, 5)) | {"repeat": 0, "recorded_steps": 200},
            _point("takeover:stall", 100, (3, 3)) | {"repeat": 1, "recorded_steps": 210},
            _point(FULL, 100, (2, 4)) | {"repeat": 0},
            _point(FULL, 100, (4, 4)) | {"repeat": 1},
        ],
        "collected": {},
        "skipped_sources": {},
        "seconds": 1.0,
        "read_from_cache": 0,
        "computed_in_this_run": 5,
        "policy": "p",
        "trained_on": "cube",
    }
    summary = summarize(result)
    assert summary["curves"]["takeover:stall"][100] == (1.0, pytest.approx(0.4))
    assert summary["unseen_by_repeat"][FULL][100] == [pytest.approx(0.3), pytest.approx(0.4)]
    assert summary["verdict"]["unseen_lift"] == pytest.approx(0.4) and summary["verdict"]["beats_full_trajectory"]
    text = markdown(result, summary, None, tmp_path / "r.md", "x")
    assert "| takeover:stall | 100 | 205 | 1.00 | 0.40 | 500 | 0.50 / 0.30 |" in text
    assert "repeated 2 times" in text


def test_each_takeover_carries_its_episodes_success():
    from bench.finetune.run import _runs_from_episodes

    def episode(operator, success, first):
        pairs = [(np.full(3, first + i, np.float32), np.zeros(10, np.float32)) for i in range(sum(operator))]
        return SimpleNamespace(operator=operator, takeover_pairs=pairs, success=success)

    flags = [False, True, True, False, True, True]  # two takeovers in each episode
    runs, successful = _runs_from_episodes([episode(flags, False, 0), episode(flags, True, 100)], seed=0)
    by_start = dict(zip((int(o[0, 0]) for o, _ in runs), successful, strict=True))
    assert by_start == {0: False, 2: False, 100: True, 102: True}
    assert sorted(len(o) for o, _ in runs) == [2, 2, 2, 2]


def test_the_selection_bears_only_on_takeover_sources_and_their_cache_keys():
    plain = FinetuneBenchConfig()
    picky = FinetuneBenchConfig(finetune=FinetuneConfig(successful_only=True, takeover_tail=33))
    assert picky.selection(FULL) == TakeoverSelection() and picky.selection("takeover:stall").tail == 33
    # points of the other sources (and the pretrained one) are found in the cache of a run without it
    assert picky.for_source(FULL).digest(FULL, 100) == plain.digest(FULL, 100)
    assert picky.for_source(None).digest("pretrained") == plain.digest("pretrained")
    assert picky.for_source("takeover:stall").digest("x") != plain.digest("x")


def test_the_grasp_window_keeps_the_steps_around_the_first_close():
    before, after = GRASP_WINDOW
    obs, act = _run(0, 80, close_at=50)
    o, a = grasp_window(obs, act)
    assert o[:, 0].tolist() == list(range(50 - before, 50 + after))
    assert (a[:, -1] > 0).sum() == after

    o, _ = grasp_window(*_run(0, 40, close_at=5))  # clipped at the start
    assert o[:, 0].tolist() == list(range(0, 5 + after))
    o, _ = grasp_window(*_run(0, 12))  # never closes: kept whole
    assert len(o) == 12


def _point(source, k, unseen_successes):
    success = {"cube": {"success_rate": 1.0}} | {
        t: {"success_rate": s / 10} for t, s in zip(("x", "y"), unseen_successes, strict=True)
    }
    return {"source": source, "samples": k, "steps": 500, "success": success}


def test_the_verdict_takes_the_default_signals_best_count_up_to_100():
    result = {
        "config": {"train_task": "cube", "unseen": ["x", "y"], "sources": ["takeover:spread", FULL]},
        "pretrained": {"cube": {"success_rate": 1.0}, "x": {"success_rate": 0.0}, "y": {"success_rate": 0.1}},
        "points": [
            _point("takeover:spread", 50, (5, 6)),  # 0.55: the best at <= 100
            _point("takeover:spread", 100, (4, 4)),
            _point("takeover:spread", 200, (10, 10)),  # beyond the goal's count
            _point(FULL, 50, (5, 5)),
            _point(FULL, 100, (9, 9)),
        ],
    }
    v = summarize(result)["verdict"]
    assert v["samples"] == 50
    assert v["unseen_lift"] == pytest.approx(0.5)
    assert v["lift_goal_met"] and v["beats_full_trajectory"]

    result["points"][3] = _point(FULL, 50, (6, 6))  # full trajectories better at the same count
    v = summarize(result)["verdict"]
    assert v["full_trajectory_at_same_count"] == pytest.approx(0.6) and not v["beats_full_trajectory"]

    # the verdict is on the first takeover source listed
    result["config"]["sources"] = ["takeover:stall", "takeover:spread", FULL]
    result["points"].append(_point("takeover:stall", 100, (7, 8)))
    v = summarize(result)["verdict"]
    assert v["source"] == "takeover:stall" and v["samples"] == 100 and v["unseen_lift"] == pytest.approx(0.7)


def test_the_config_refuses_unknown_sources_and_bad_counts_before_anything_runs():
    assert FinetuneBenchConfig(sources=(GRASP, FULL, "takeover:spread")).sources[0] == GRASP
    for bad in ("expert:lift", "takeover:nope", "spread"):
        with pytest.raises(ValueError, match=f"unknown source '{bad}'"):
            FinetuneBenchConfig(sources=(bad,))
    for counts in ((), (0,), (20, 2.5)):
        with pytest.raises(ValueError, match="counts must be integers >= 1"):
            FinetuneBenchConfig(counts=counts)
    assert FinetuneBenchConfig(hand_back="operator", stride=2).stride == 2
    with pytest.raises(ValueError, match="hand_back must be one of"):
        FinetuneBenchConfig(hand_back="later")
    assert FinetuneBenchConfig(hand_back="continuous", return_after=30).return_after == 30
    for hand_back in ("operator", "budgeted"):  # the operator (or the budget) hands back: not the calm steps
        with pytest.raises(
            ValueError, match=f"return_after applies to the continuous hand-back only, not to '{hand_back}'"
        ):
            FinetuneBenchConfig(hand_back=hand_back, return_after=30)
    for stride in (0, 1.5, True):
        with pytest.raises(ValueError, match="stride must be an integer >= 1"):
            FinetuneBenchConfig(stride=stride)
    with pytest.raises(ValueError, match="repeats must be an integer >= 1"):
        FinetuneBenchConfig(repeats=0)


def test_takeovers_are_collected_again_when_the_signal_is_recalibrated(tmp_path):
    from bench.finetune.run import _signal_digest

    folder = tmp_path / "signals" / "stall"
    assert _signal_digest(str(tmp_path), "takeover:stall") is None  # not trained: nothing to tell apart
    folder.mkdir(parents=True)
    (folder / "config.json").write_text('{"calibration": {"threshold": 0.3}}')
    first = _signal_digest(str(tmp_path), "takeover:stall")
    (folder / "config.json").write_text('{"calibration": {"threshold": 0.4}}')
    assert first is not None and _signal_digest(str(tmp_path), "takeover:stall") != first
    assert _signal_digest(str(tmp_path), FULL) is None


def test_the_cli_names_a_bad_source(capsys):
    import torch

    from hitl.cli import main

    threads = torch.get_num_threads()
    assert main(["bench", "finetune", "--sources", "takeover:nope", "--threads", str(threads + 1)]) == 2
    assert "unknown source 'takeover:nope'" in capsys.readouterr().err
    assert torch.get_num_threads() == threads  # refused before it set anything up


def _ep(to_grasp, to_origin):
    info = {"max_lift": 0.0, "first_close_step": None if to_grasp is None else 40}
    return SimpleNamespace(
        success=False, info=info | {"first_close_to_grasp_m": to_grasp, "first_close_to_origin_m": to_origin}
    )


def test_first_close_summary_counts_the_closes_and_takes_medians():
    fc = first_close_summary([_ep(0.06, 0.01), _ep(None, None), _ep(0.02, 0.05), _ep(0.07, 0.03)])
    assert fc == {"episodes": 4, "closed": 3, "median_to_grasp_m": 0.06, "median_to_origin_m": 0.03}
    assert first_close_summary([_ep(None, None)])["median_to_grasp_m"] is None
    assert first_close_summary([SimpleNamespace(success=True, info={})]) is None  # a task that records none


def test_the_report_shows_where_the_gripper_closes_for_the_points_that_recorded_it(tmp_path):
    def success(fc):
        return {t: {"success_rate": 0.0, "first_close": fc} for t in ("cube", "x", "y")}

    fc = {"episodes": 20, "closed": 15, "median_to_grasp_m": 0.065, "median_to_origin_m": 0.021}
    result = {
        "config": {
            "train_task": "cube",
            "unseen": ["x", "y"],
            "sources": [FULL],
            "eval_episodes": 20,
            "eval_seed": 1,
            "hand_back": "continuous",
            "cooldown": 10,
        },
        "pretrained": success(None),  # evaluated before first closes were recorded
        "points": [{"source": FULL, "samples": 100, "steps": 500, "success": success(fc)}],
        "collected": {},
        "skipped_sources": {},
        "seconds": 1.0,
        "read_from_cache": 0,
        "computed_in_this_run": 2,
        "policy": "p",
        "trained_on": "cube",
    }
    text = markdown(result, summarize(result), None, tmp_path / "r.md", "hitl bench finetune")
    assert f"| {FULL} | 100 | 15/20 / 15/20 | 6.5 / 6.5 | 2.1 / 2.1 |" in text
    assert "with 50/50 mini-batches" in text  # the default mix; a run's own ratio is named
    result["config"]["finetune"] = {"ratio": 0.8}
    assert "with 80/20 mini-batches" in markdown(result, summarize(result), None, tmp_path / "r.md", "x")
    assert "| pretrained | 0 | " not in text.split("Where the gripper first closes")[1]
    assert "Takeover sources keep" not in text  # every takeover step, by default
    result["config"]["finetune"] = {"successful_only": True, "takeover_tail": 33}
    result["points"][0]["recorded_steps"] = 180
    text = markdown(result, summarize(result), None, tmp_path / "r.md", "x")
    assert "Takeover sources keep only takeovers in episodes that succeeded" in text and "last 33 steps" in text
    assert f"| {FULL} | 100 | 180 | 0.00 | 0.00 | 500 |" in text

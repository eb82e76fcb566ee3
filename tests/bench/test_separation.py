import numpy as np
import pytest

from bench.separation import auroc, shift_separation
from policy.checkpoint import save_policy
from tests.helpers import tiny_policy


def test_auroc_golden_values():
    assert auroc(np.array([0.0, 1.0]), np.array([2.0, 3.0])) == 1.0
    assert auroc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 0.0
    assert auroc(np.ones(3), np.ones(4)) == 0.5
    assert auroc(np.array([0.0, 2.0]), np.array([1.0, 3.0])) == 0.75


def test_separation_scores_every_state_of_both_tasks_and_names_what_it_skipped(tmp_path):
    policy = tiny_policy("lift-cube")
    folder = save_policy(policy, tmp_path / "lift", {"task": "lift-cube"})
    report = shift_separation(
        policy,
        folder,
        "lift-cube",
        ["lift-hammer"],
        episodes=1,
        seed=7,
        signals=["denoising", "random", "thrifty"],
        progress=False,
    )
    assert report.states == {"lift-cube": 150, "lift-hammer": 150}  # the untrained policy never lifts
    assert set(report.auroc) == {"denoising", "random"}
    assert all(0.0 <= v <= 1.0 for row in report.auroc.values() for v in row.values())
    assert "thrifty" in report.skipped and "train-signal" in report.skipped["thrifty"]
    text = report.markdown()
    assert "| denoising |" in text and "- thrifty:" in text
    with pytest.raises(ValueError, match="unknown signals"):
        shift_separation(policy, folder, "lift-cube", ["lift-hammer"], signals=["nope"], progress=False)


def test_replay_series_gives_each_episode_its_own_history_in_order():
    """A stateful signal (a per-robot step counter) sees every episode from its first step, in order."""
    from policy.signals.base import Scores, StepSet
    from policy.signals.sampling import replay_series

    class Counter:
        def __init__(self):
            self.seen: dict[int, int] = {}

        def reset(self, ids):
            for i in ids:
                self.seen.pop(int(i), None)

        def score(self, batch):
            out = []
            for i in batch.robot_ids:
                self.seen[int(i)] = self.seen.get(int(i), 0) + 1
                out.append(self.seen[int(i)])
            return Scores(np.array(out, dtype=float))

    lengths = [3, 5, 2]
    n = sum(lengths)
    episode = np.repeat(np.arange(3), lengths)
    t = np.concatenate([np.arange(k) for k in lengths])
    steps = StepSet(
        obs=np.zeros((n, 1, 4), np.float32),
        action=np.zeros((n, 1, 10), np.float32),
        current=np.zeros((n, 10), np.float32),
        episode=episode,
        t=t,
        last=np.zeros(n, np.int64),
        success=np.zeros(n, bool),
        names=["a", "b", "c"],
    )
    series = replay_series(Counter(), steps, steps.episodes(), progress=False, desc="", batch=2)
    assert [s.tolist() for s in series] == [[1, 2, 3], [1, 2, 3, 4, 5], [1, 2]]

import numpy as np
import pytest

from policy.checkpoint import save_policy
from policy.separation import auroc, shift_separation
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

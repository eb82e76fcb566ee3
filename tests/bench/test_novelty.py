import numpy as np
import torch

from bench.novelty import task_novelty
from policy.checkpoint import save_policy
from policy.signal_data import policy_rollouts
from policy.signals.spread import observation_novelty
from tests.helpers import tiny_policy


def test_novelty_summarises_every_state_of_each_task_against_the_gate(tmp_path):
    policy = tiny_policy("lift-cube")
    folder = save_policy(policy, tmp_path / "lift", {"task": "lift-cube"})
    report = task_novelty(policy, folder, ["lift-cube", "lift-hammer"], episodes=1, seed=7, gate=0.0, progress=False)
    assert list(report.tasks) == ["lift-cube", "lift-hammer"] and report.seeds == [7]
    hammer = report.tasks["lift-hammer"]
    assert hammer.episodes == 1 and hammer.states == 150  # the untrained policy never lifts
    steps = policy_rollouts(policy, folder, "lift-hammer", [7], progress=False)  # the cached rollouts
    novelty = observation_novelty(policy.normalize_obs(torch.as_tensor(steps.obs))).double().numpy()
    assert hammer.max == float(novelty.max()) and hammer.min == float(novelty.min())
    assert hammer.share_over_gate == float((novelty > 0).mean())
    assert hammer.min <= hammer.median <= hammer.max
    strict = task_novelty(policy, folder, ["lift-hammer"], episodes=1, seed=7, gate=np.inf, progress=False)
    assert strict.tasks["lift-hammer"].share_over_gate == 0.0
    assert "| lift-hammer | 1 |" in report.markdown()
    assert report.to_dict()["tasks"]["lift-cube"]["states"] == report.tasks["lift-cube"].states

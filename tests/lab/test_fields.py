import numpy as np
import torch

from lab.fields import rollout_fields
from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.evaluate import summarize
from policy.uncertainty import UncertaintyConfig
from sim.tasks.lift import LIFT_OBS


def test_rollout_fields_scores_and_keeps_every_step_of_every_robot():
    torch.manual_seed(0)
    cfg = DiffusionPolicyConfig(
        obs_dim=LIFT_OBS.dim,
        network="mlp",
        mlp_hidden=32,
        obs_encoder_dims=(16,),
        step_embed_dim=8,
        num_inference_steps=3,
    )
    policy = DiffusionPolicy(cfg).eval()
    rng = np.random.default_rng(0)
    low = np.r_[[-0.1, -0.1, 0.9], [-1] * 6, [-1]]
    high = np.r_[[0.1, 0.1, 1.0], [1] * 6, [1]]
    policy.fit_normalizers(rng.normal(size=(64, LIFT_OBS.dim)), rng.uniform(low, high, size=(64, 10)))
    unc = UncertaintyConfig(num_samples=16)
    episodes, _ = rollout_fields(policy, "lift-cube", [5, 6], unc, n_envs=2, progress=False)
    assert [e.seed for e in episodes] == [5, 6]
    for e in episodes:
        assert len(e.uncertainty) == e.steps == len(e.fields) == len(e.context) == len(e.probe_inputs) > 0
        assert [f.U for f in e.fields] == e.uncertainty  # the same steps' fields, in order
        assert np.isfinite(e.uncertainty).all() and "max_lift" in e.info
    s = summarize(episodes)
    assert s["episodes"] == 2 and np.isfinite(s["uncertainty"]["p95"])

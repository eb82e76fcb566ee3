"""``hitl bench uncertainty``: times what the fleet serves and compares the mixture back ends."""

import subprocess
import sys

import numpy as np
import torch

from bench.uncertainty import bench_uncertainty, versus_reference
from policy.checkpoint import load_policy
from policy.devices import prepare_for_serving
from policy.signals import load_signal
from policy.uncertainty import UncertaintyConfig
from tests.helpers import tiny_policy_folder


def test_the_bench_times_the_served_policy_and_signals(tmp_path):
    folder = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    policy, _ = load_policy(folder)
    prepare_for_serving(policy, "cpu")
    rng = np.random.default_rng(0)
    obs = rng.uniform(-0.2, 1.0, (12, policy.config.obs_horizon, policy.config.obs_dim)).astype(np.float32)
    centers = rng.uniform(0.3, 0.7, (12, 10)).astype(np.float32)
    out = bench_uncertainty(
        policy, obs, centers, (1, 4), repeats=1, agreement_states=12, asking=load_signal(policy, folder, "spread"),
        progress=False,
    )  # fmt: skip
    assert out["traced"] and out["device"] == "cpu" and out["gmm_backend"] == "auto"
    assert [r["fleet_size"] for r in out["fleet"]] == [1, 4]
    for row in out["fleet"]:
        total = row["ddim_ms_per_robot_step"] + row["denoising_signal_ms_per_robot_step"]
        assert np.isclose(row["policy_plus_uncertainty_ms_per_robot_step"], total)
        assert row["spread_ms_per_robot_step"] > 0 and row["gmm_sklearn_ms_per_robot_step"] > 0
    assert out["goal"]["met"] is False  # no fleet of 16 was measured: the goal is not claimed
    assert out["goal"]["uncertainty_over_ddim_met"] is False  # nor of 32
    agree = out["agreement"]
    assert agree["states"] == 12 and sum(agree["n_histogram"]["auto"]) == 12
    assert 0.0 <= agree["auto_vs_sklearn"]["n_agreement"] <= 1.0
    assert len(agree["numba_em_iterations_mean"]) == 4 and min(agree["numba_em_iterations_max"]) >= 1
    assert agree["versus_s128"] is None  # the probe is the paper's S = 128: nothing to compare with
    assert agree["s128_redrawn"]["states"] == 12 and -1.0 <= agree["s128_redrawn"]["spearman"] <= 1.0


def test_a_smaller_probe_is_compared_with_the_papers_on_the_same_states(tmp_path):
    policy, _ = load_policy(tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5))
    prepare_for_serving(policy, "cpu")
    rng = np.random.default_rng(1)
    obs = rng.uniform(-0.2, 1.0, (40, policy.config.obs_horizon, policy.config.obs_dim)).astype(np.float32)
    centers = rng.uniform(0.3, 0.7, (40, 10)).astype(np.float32)
    out = bench_uncertainty(policy, obs, centers, (2,), 1, UncertaintyConfig(num_samples=16), 40, progress=False)
    versus = out["agreement"]["versus_s128"]
    assert out["samples_per_robot"] == 16 and versus["states"] == 40
    assert -1.0 <= versus["spearman"] <= 1.0 and 0.0 <= versus["flagged_overlap"] <= 1.0
    assert versus["flagged_by_reference"] == 2  # above the 95% quantile of 40 states


def test_agreement_with_the_reference_probe_golden_values():
    u = torch.arange(100, dtype=torch.float64)
    same = versus_reference(u * 3.0, u)  # a rescaled U ranks and flags exactly as the reference
    assert np.isclose(same["spearman"], 1.0) and same["flagged_overlap"] == 1.0 and same["flagged_by_reference"] == 5
    flipped = versus_reference(-u, u)  # the reverse order flags none of the reference's states
    assert np.isclose(flipped["spearman"], -1.0) and flipped["flagged_overlap"] == 0.0
    half = u.clone()
    half[[99, 98]] = -1.0  # two of the reference's five top states fall to the bottom
    assert versus_reference(half, u)["flagged_overlap"] == 3 / 5


def test_a_fleet_larger_than_the_states_is_refused(tmp_path):
    import pytest

    policy, _ = load_policy(tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5))
    prepare_for_serving(policy, "cpu")
    with pytest.raises(ValueError, match="fleet size 8 needs 8 states"):
        bench_uncertainty(policy, np.zeros((4, 1, 26), np.float32), np.zeros((4, 10), np.float32), (8,), progress=False)


def test_a_missing_device_is_a_clear_command_line_error(tmp_path):
    folder = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    for argv in (
        ["bench", "uncertainty", "--policy", str(folder), "--device", "cuda:99", "--quiet"],
        ["bench", "fleet", "--robots", "2", "--device", "cuda:99", "--quiet"],
    ):
        proc = subprocess.run([sys.executable, "-m", "hitl.cli", *argv], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert "'cuda:99'" in proc.stderr and "Traceback" not in proc.stderr


def test_the_asking_signal_is_timed_when_the_policy_has_it_and_named_when_asked_for(tmp_path):
    import json
    import shutil

    folder = tiny_policy_folder(tmp_path / "policy", "lift-cube", 0.5)
    shutil.rmtree(folder / "signals" / "spread")
    base = ["bench", "uncertainty", "--policy", str(folder), "--episodes", "1", "--fleet-sizes", "2"]
    base += ["--repeats", "1", "--quiet", "--json"]
    proc = subprocess.run([sys.executable, "-m", "hitl.cli", *base], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert "spread not timed" in out["asking_skipped"] and "spread_ms_per_robot_step" not in out["fleet"][0]
    asked = subprocess.run(
        [sys.executable, "-m", "hitl.cli", *base, "--asking", "spread"], capture_output=True, text=True, timeout=300
    )
    assert asked.returncode == 2 and "spread" in asked.stderr and "Traceback" not in asked.stderr

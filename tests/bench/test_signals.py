import numpy as np

from bench.signals import bench_signals
from policy.signals import make_signal
from policy.signals.base import StepSet
from tests.helpers import tiny_policy


def _steps(policy, n: int = 6) -> StepSet:
    rng = np.random.default_rng(0)
    cfg = policy.config
    current = np.tile([0.0, 0.0, 0.9, 1, 0, 0, 0, 1, 0, -1], (n, 1)).astype(np.float32)
    return StepSet(
        obs=rng.normal(size=(n, cfg.obs_horizon, cfg.obs_dim)).astype(np.float32),
        action=np.repeat(current[:, None], cfg.action_horizon, axis=1),
        current=current,
        episode=np.zeros(n, dtype=np.int64),
        t=np.arange(n),
        last=np.full(n, n - 1),
        success=np.ones(n, dtype=bool),
        names=["episode-0"],
    )


def test_bench_signals_times_each_signal_and_ddim_per_robot_step():
    policy = tiny_policy()
    signals = {"denoising": make_signal("denoising", policy, {"num_samples": 8})}
    report = bench_signals(signals, _steps(policy), fleet_size=4, repeats=2, progress=False)
    row = report["signals"]["denoising"]
    assert report["fleet_size"] == 4 and report["repeats"] == 2
    assert row["ms_per_robot_step"] > 0 and row["ddim_ms_per_robot_step"] > 0
    assert row["policy_net_rows_per_robot_step"] == 8  # one ε_θ call on S = 8 probe samples per robot
    assert row["cost_over_denoising"] == 1.0

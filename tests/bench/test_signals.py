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


def test_bench_signals_measures_a_variant_beside_the_saved_signal(tmp_path, capsys):
    import json

    from hitl.cli import main
    from tests.helpers import tiny_policy_folder

    folder = tiny_policy_folder(tmp_path / "lift", "lift-cube", threshold=1.0)
    argv = ["bench", "signals", "--policy", str(folder), "--signals", "denoising,denoising:center=chunk,nope:x=1"]
    # an unknown name is refused before anything runs, with a message naming it
    assert main(argv + ["--episodes", "1", "--robots", "2", "--repeats", "1", "--json", "--quiet"]) != 0
    assert "nope" in capsys.readouterr().err
    argv[-1] = "denoising,denoising:center=chunk,denoising:centre=chunk"
    assert main(argv + ["--episodes", "1", "--robots", "2", "--repeats", "1", "--json", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["signals"]) == {"denoising", "denoising:center=chunk"}
    rows = {k: v["policy_net_rows_per_robot_step"] for k, v in out["signals"].items()}
    assert rows["denoising:center=chunk"] == rows["denoising"]  # the same probe, moved to where the chunk goes
    assert "centre" in out["skipped"]["denoising:centre=chunk"]  # a setting the signal does not have: named

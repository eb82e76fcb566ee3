"""``hitl bench fleet``'s measurement on a real fleet (pool and ray back ends): steps, latency, memory, overhead."""

import os

import numpy as np
import pytest

from bench.fleet import available_workers, fleet_goals, fleet_throughput


def test_a_pooled_fleet_steps_every_robot_and_reports_its_memory(tmp_path):
    out = fleet_throughput("lift-cube", 3, 2.0, tmp_path / "var", worker="pool", robots_per_process=2)
    assert out["worker"] == "pool" and out["worker_processes"] == 2  # 3 robots, 2 per process
    assert out["env_steps_per_s"] > 0 and out["ticks_per_s"] > 0
    assert out["commands_applied"] > 0  # robot 0 is teleoperated through the fleet's mailbox
    assert out["server_rss_mb"] > out["server_rss_before_fleet_mb"] > 0
    assert out["worker_peak_rss_mb"] > 0 and out["workers_rss_mb_per_robot"] > 0
    assert out["workers_peak_rss_mb_per_robot"] >= out["workers_rss_mb_per_robot"] * 0.99  # a peak is no lower
    assert np.isclose(out["server_peak_rss_mb_per_robot"] * 3, out["server_peak_rss_mb"])
    assert out["workers_cpu_ms_per_env_step"] > 0
    # the physics processes' CPU only: together with the loop's, no more than the machine's cores give
    cores = os.cpu_count() or 1
    used = (out["workers_cpu_ms_per_env_step"] + out["loop_cpu_ms_per_env_step"]) * out["env_steps_per_s"] / 1e3
    assert used <= cores * 1.05


def test_the_goals_say_per_back_end_whether_this_run_met_them():
    rows = [
        {"robots": 8, "backend": "process", "share_of_raw": 0.9},  # not the goal's size: not judged
        {"robots": 16, "backend": "process", "share_of_raw": 0.49},
        {"robots": 16, "backend": "pool", "share_of_raw": 0.7},
    ]
    goals = fleet_goals(rows, {"process": 5.2, "pool": 0.4})
    assert goals["share_of_raw_at_16"] == 0.7 and goals["share_of_raw_at_16_met"] == {"process": False, "pool": True}
    assert goals["server_mb_per_added_robot_met"] == {"process": False, "pool": True}
    assert fleet_goals(rows[:1], {})["share_of_raw_at_16_met"] == {}  # no fleet of 16: nothing claimed


def test_a_ray_fleet_steps_every_robot_and_reports_rays_overhead(tmp_path, ray_local):
    out = fleet_throughput("lift-cube", 3, 2.0, tmp_path / "var", worker="ray", robots_per_process=2)
    assert out["worker"] == "ray" and out["worker_processes"] == 2  # 3 robots, 2 per actor
    assert out["env_steps_per_s"] > 0 and out["commands_applied"] > 0
    assert out["workers_cpu_ms_per_env_step"] > 0  # the actors' processes, found by their pids
    assert out["ray_api_ms_per_tick"] > 0 and out["ray_api_us_per_call"] > 0
    assert out["backend_processes_cpu_ms_per_env_step"] > 0  # the local instance's raylet and GCS work too


def test_a_fleet_with_its_inference_on_ray_reports_the_actors_call_and_compute_time(tmp_path, ray_local):
    out = fleet_throughput("lift-cube", 2, 2.0, tmp_path / "var", worker="pool", robots_per_process=2, inference="ray")
    assert out["inference"] == "ray" and out["env_steps_per_s"] > 0 and out["commands_applied"] > 0
    call, compute = out["inference_call_ms"], out["inference_actor_compute_ms"]
    assert 0 < compute < call  # one call per tick: the actor's network time, inside the loop's wait for it
    assert out["inference_ray_overhead_ms_per_tick"] == pytest.approx(call - compute)


def test_the_default_back_ends_are_those_installed_here():
    assert available_workers() == ("process", "pool", "ray")  # the test extra installs Ray


def test_compare_puts_each_figure_beside_the_previous_releases_row():
    """Rows meet by size and back end (an earlier file names it ``worker``); a figure only one side holds
    is left out, and the previous file's provenance is kept."""
    from bench.fleet import compare_with

    now = {
        "sizes": [
            {
                "robots": 16,
                "backend": "pool",
                "env_steps_per_s": 140.0,
                "loop_cpu_ms_per_env_step": 6.5,
                "loop_own_cpu_ms_per_env_step": 0.6,
                "signals_cpu_ms_per_env_step": {"denoising": 1.8},
            },
            {"robots": 8, "backend": "pool", "env_steps_per_s": 150.0},
        ]
    }
    before = {
        "provenance": {"commit": "c" * 40},
        "sizes": [{"robots": 16, "worker": "pool", "env_steps_per_s": 223.0, "loop_cpu_ms_per_env_step": 3.9}],
    }
    out = compare_with(now, before)
    assert out["before"] == {"commit": "c" * 40}
    [row] = out["rows"]
    assert row["robots"] == 16 and row["env_steps_per_s"] == {"before": 223.0, "now": 140.0}
    assert row["loop_cpu_ms_per_env_step"] == {"before": 3.9, "now": 6.5}
    assert "loop_own_cpu_ms_per_env_step" not in row and row["signals"] == {}


def test_a_fleet_of_a_seeing_policy_reports_its_encoders_share_and_raw_counts_rendering(tmp_path):
    from bench.fleet import raw_throughput
    from tests.server.fleet.test_fleet_vision import _seeing_policy_folder

    policy = _seeing_policy_folder(tmp_path / "eyes")
    out = fleet_throughput(
        "lift-cube", 2, 2.0, tmp_path / "var", worker="pool", robots_per_process=2, policy=policy, signal="denoising"
    )
    assert out["env_steps_per_s"] > 0 and out["encode_cpu_ms_per_env_step"] > 0
    assert out["asking_signal"] == "denoising"
    assert raw_throughput("lift-cube", 1, 1.0, images=True) > 0  # its processes render the task's cameras

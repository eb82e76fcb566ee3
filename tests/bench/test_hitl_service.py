"""``hitl bench hitl-service``: the same seeds through a real ``hitl serve`` with the operator bot and in
process give the same per-episode numbers."""

from bench.hitl_service import bench_hitl_service, fleet_seeds
from policy.checkpoint import load_policy
from policy.signals import make_signal, save_signal
from tests.helpers import tiny_policy_folder


def test_the_service_path_and_the_in_process_run_give_the_same_numbers(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=1e9)
    save_signal(make_signal("random", load_policy(policy)[0], {"rate": 0.3}), policy)
    out = bench_hitl_service("lift-cube", policy, episodes=3, signal="random", budget=4, progress=False)
    assert out["seeds"] == fleet_seeds(0, 3) == [1, 1001, 2001]
    # random asks on 30% of the policy's steps, each request a 4-step takeover by the bot
    assert all(p["service"] is not None and p["service"]["events"] >= 3 for p in out["per_seed"])
    assert out["identical"], out["per_seed"]
    assert out["service"] == out["in_process"]

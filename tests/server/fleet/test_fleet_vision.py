"""A fleet of robots whose policy sees cameras: real in-process workers render the task's cameras, the
controller encodes them, episodes and takeover segments record the frames, fine-tuning reads them back."""

import numpy as np
import pytest
import torch

from policy.checkpoint import layout_info, load_policy, save_calibration, save_policy
from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.finetune import FinetuneConfig, FinetuneDataError, finetune_policy
from server.db import make_engine, migrate, session_factory
from server.fleet.fleet import Fleet
from server.settings import RobotGroup, Settings
from server.workers import in_process_workers
from sim.registry import make_task
from sim.spaces import TeleopCommand
from storage.episodes import read_episode
from storage.segments import read_segment
from storage.takeovers import load_takeovers

UP = TeleopCommand((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), 1.0)


def _seeing_policy_folder(folder):
    task = make_task("lift-cube", images=True)
    torch.manual_seed(0)
    cfg = DiffusionPolicyConfig(
        obs_dim=task.obs_spec.dim,
        network="mlp",
        mlp_hidden=16,
        step_embed_dim=8,
        num_inference_steps=2,
        obs_encoder_dims=(),
        cameras=task.cameras,
        image_channels=8,
        image_keypoints=4,
        image_features=8,
    )
    policy = DiffusionPolicy(cfg)
    rng = np.random.default_rng(0)
    acts = np.concatenate(
        [rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0], (64, 3)), np.tile([0, 1, 0, 1, 0, 0, -1], (64, 1))], 1
    )
    policy.fit_normalizers(rng.normal(size=(64, cfg.obs_dim)), acts)
    save_policy(policy.eval(), folder, {"task": "lift-cube", **layout_info(task.obs_spec)})
    save_calibration(folder, {"threshold": -1.0, "quantile": 0.95, "samples": 0})  # asks at once
    return folder


def test_a_fleet_of_seeing_robots_renders_encodes_and_records_what_they_saw(tmp_path):
    policy = _seeing_policy_folder(tmp_path / "eyes")
    s = Settings(
        data_dir=tmp_path / "var",
        robots=[RobotGroup(task="lift-cube", count=2, policy=policy)],
        inference={"trace_policies": False},
        controller={"signal": "denoising"},
        recording={"flush_seconds": 0, "episodes": True},
    )
    migrate(s.db_url)
    fleet = Fleet(s, session_factory(make_engine(s.db_url)), in_process_workers())
    fleet.spawn_workers()
    try:
        fleet.tick()  # threshold -1: both ask at once, on what their cameras showed
        assert {fleet.view(r).mode for r in (0, 1)} == {"waiting"}
        frame = fleet.view(0).frame
        assert set(frame.images) == {"front", "wrist"} and frame.obs.shape == (11,)  # the robot's own state
        fleet.claim(0, "op")
        for _ in range(3):
            fleet.command(0, "op", UP)
            fleet.tick()
        fleet.release(0, "op")
        fleet.tick()
        [segment] = _segment_paths(fleet)
        seg = read_segment(segment)
        frames = seg.frames("wrist")
        assert frames.shape == (len(seg.steps), 84, 84, 3) and len(seg.steps) >= 3
        data = load_takeovers([segment], obs_dim=11, cameras=["front", "wrist"])
        assert data.images["front"].shape == (len(seg.steps), 84, 84, 3) and not data.skipped
        # the nightly job's step: the policy fine-tunes on what its takeovers recorded, frames included
        parent, _ = load_policy(policy)
        arrays = data.arrays(1, 1)
        cfg = FinetuneConfig(steps=2, batch_size=4, warmup_steps=1)
        child, history = finetune_policy(parent, arrays, arrays, cfg, progress=False)
        assert history["takeover_samples"] == len(seg.steps)
        encoder = [k for k in parent.state_dict() if k.startswith("image_encoder.")]
        assert encoder and any(not torch.equal(child.state_dict()[k], parent.state_dict()[k]) for k in encoder)
        with pytest.raises(FinetuneDataError, match="the policy sees"):  # frames missing: refused by name
            finetune_policy(parent, {k: v for k, v in arrays.items() if "images" not in k}, arrays, cfg, progress=False)
    finally:
        fleet.stop()  # closes the episode files
    episode = read_episode(next((s.data_dir / "episodes").glob("robot000_*.mcap")), recover=True)
    assert [c["name"] for c in episode.cameras] == ["front", "wrist"]
    assert episode.frames("front").shape == (len(episode), 84, 84, 3) and len(episode) >= 4


def _segment_paths(fleet):
    from server.db import SegmentRecord

    with fleet.sessions() as s:
        return [fleet.settings.data_dir / row.path for row in s.query(SegmentRecord).order_by(SegmentRecord.id)]

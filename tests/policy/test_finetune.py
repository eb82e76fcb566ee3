"""Fine-tuning's parts: the promotion gate, the step count, resumable training, the segment reader."""

from dataclasses import replace

import numpy as np
import pytest

from policy.finetune import FinetuneConfig, FinetuneDataError, TaskResult, finetune_policy, gate
from policy.train import TrainConfig, TrainState, train_policy
from sim.tasks.lift import LIFT_OBS
from storage import keys
from storage.segments import SegmentWriter
from storage.takeovers import load_takeovers
from tests.helpers import state_equal, tiny_policy


def _results(**rates):
    return {t: TaskResult(t, 10, round(r * 10), 7) for t, r in rates.items()}


def test_the_gate_promotes_only_a_version_better_on_targets_and_not_worse_on_training():
    parent = _results(train=0.9, a=0.2, b=0.4)
    ok = gate(parent, _results(train=0.9, a=0.5, b=0.5), "train", ["a", "b"], tolerance=0.05)
    assert ok.promote and ok.evidence["target_success"] == {"parent": pytest.approx(0.3), "candidate": 0.5}
    within = gate(parent, _results(train=0.9 - 0.1, a=0.9, b=0.9), "train", ["a", "b"], tolerance=0.1)
    assert within.promote  # a drop of exactly the tolerance is allowed
    worse = gate(parent, _results(train=0.7, a=0.9, b=0.9), "train", ["a", "b"], tolerance=0.1)
    assert not worse.promote and worse.reason.startswith("worse on train: 0.70 against 0.90")
    same = gate(parent, _results(train=1.0, a=0.2, b=0.4), "train", ["a", "b"], tolerance=0.05)
    assert not same.promote and same.reason.startswith("not better on a, b: 0.30 against 0.30")
    small = gate(parent, _results(train=0.9, a=0.3, b=0.4), "train", ["a", "b"], tolerance=0.05, min_gain=0.1)
    assert not small.promote and "needs more than +0.10" in small.reason
    # same task as target and training: must improve on it
    assert gate(_results(t=0.5), _results(t=0.6), "t", ["t"], 0.05).promote
    assert not gate(_results(t=0.5), _results(t=0.5), "t", ["t"], 0.05).promote


def test_the_gate_refuses_to_compare_different_evaluations():
    with pytest.raises(ValueError, match="not evaluated"):
        gate(_results(train=1.0), _results(train=1.0, a=1.0), "train", ["a"], 0.05)
    other_seed = {"train": TaskResult("train", 10, 9, 8)}
    with pytest.raises(ValueError, match="different episodes"):
        gate(_results(train=0.9), other_seed, "train", ["train"], 0.05)


def test_steps_scale_with_the_takeover_data():
    cfg = FinetuneConfig(batch_size=64, ratio=0.5, passes=60, min_steps=300, max_steps=6000)
    assert cfg.steps_for(10) == 300
    assert cfg.steps_for(1000) == 1875  # 60 * 1000 / 32
    assert cfg.steps_for(10**6) == 6000
    assert FinetuneConfig(steps=7).steps_for(10**6) == 7
    for bad in ({"ratio": 0}, {"ratio": 1.5}, {"min_steps": 10, "max_steps": 5}, {"steps": 0}, {"tolerance": 1}):
        with pytest.raises(ValueError):
            FinetuneConfig(**bad)
    with pytest.raises(ValueError, match="overlap the gate's 50000..50019"):
        FinetuneConfig(fit_seed=50_010)
    with pytest.raises(ValueError, match="fit_episodes"):
        FinetuneConfig(fit_episodes=0)
    assert FinetuneConfig(fit_seed=50_020).fit_seed == 50_020  # right after the gate's seeds


def _fit_signal(policy, threshold=4.0):
    from policy.signals import make_signal

    signal = make_signal("choice-stall", policy, {"num_samples": 4, "choice_patience": 2})
    signal.calibration = {
        "threshold": 1.0,
        "choice": {"threshold": threshold, "stride": 0.01},
        "stall": {"threshold": 0.5, "stride": 0.01},
    }
    return signal


def test_fitting_on_own_episodes_needs_successes_and_leaves_the_threshold_without_them():
    """Real rollouts of a policy that never lifts the cube: each step's score is kept, and nothing is fitted."""
    from policy.finetune import fit_threshold_on_own_episodes

    policy = tiny_policy()
    signal = _fit_signal(policy)
    evidence = fit_threshold_on_own_episodes(
        policy, signal, "choice-stall", ["lift-cube"], "familiar", 2, 60_000, progress=False
    )
    assert evidence["successes"] == 0 and evidence["factor"] is None and "fewer than" in evidence["why"]
    assert signal.calibration["choice"]["threshold"] == 4.0


def test_fitting_on_own_episodes_raises_the_threshold_to_the_most_doubtful_successful_episode(monkeypatch):
    """The rollouts stand in for a policy that lifts the cube (no tiny policy does in a test's time)."""
    import policy.evaluate
    from policy.evaluate import PolicyEpisode
    from policy.finetune import MIN_FIT_SUCCESSES, fit_threshold_on_own_episodes

    levels = [0.5] * MIN_FIT_SUCCESSES + [1.1, 1.3]  # the last two over the threshold of 1

    def rollouts(policy, task, seeds, n_envs, progress, signals):
        eps = [PolicyEpisode(task, s, True, 3, {}) for s in seeds]
        for ep, level in zip(eps, [*levels, 9.0], strict=False):
            ep.signal_scores = [{"choice-stall": v} for v in (0.1, level, level, 0.1)]
        eps[-1].success = False  # a failed episode's doubt is the operator's business: not fitted on
        return eps, {}

    monkeypatch.setattr(policy.evaluate, "rollout_policy", rollouts)
    signal = _fit_signal(tiny_policy())
    n = len(levels) + 1
    evidence = fit_threshold_on_own_episodes(
        signal.policy, signal, "choice-stall", ["lift-cube"], "familiar", n, 60_000, progress=False
    )
    assert evidence["successes"] == len(levels) and evidence["asked"] == 2
    assert evidence["factor"] == pytest.approx(max(levels))
    assert signal.calibration["choice"]["threshold"] == pytest.approx(4.0 * max(levels))
    assert signal.calibration["choice"]["own_episodes"]["seed"] == 60_000
    assert signal.calibration["stall"]["threshold"] == 0.5  # the new-scene half is fitted on other tasks


def _data(n=40, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, 1, LIFT_OBS.dim)).astype(np.float32)  # tiny_policy()'s: lift-cube's observations
    act = np.concatenate(
        [rng.uniform([-0.1, -0.1, 0.85], [0.1, 0.1, 1.0], (n, 3)), np.tile([0, 1, 0, 1, 0, 0, -1.0], (n, 1))], 1
    ).astype(np.float32)[:, None]
    return {keys.OBS: obs, keys.ACTION: act}


def test_training_resumed_from_a_checkpoint_equals_an_uninterrupted_run(tmp_path):
    cfg = TrainConfig(steps=10, batch_size=8, warmup_steps=2, val_every=100)
    straight, _ = train_policy(tiny_policy(), _data(), None, cfg, progress=False)
    saved = []

    def keep(state):
        state.save(tmp_path / f"at{state.step}")
        state.save(tmp_path / "rolling")  # one folder saved over and over: the latest complete state
        saved.append(tmp_path / f"at{state.step}")

    train_policy(tiny_policy(), _data(), None, cfg, progress=False, checkpoint=keep, checkpoint_every=4)
    assert [TrainState.load(p).step for p in saved] == [4, 8, 10]
    assert TrainState.load(tmp_path / "rolling").step == 10
    assert [d.name for d in (tmp_path / "rolling").glob("step-*")] == ["step-00000010"]
    (tmp_path / "rolling" / "step-00000010" / TrainState.META).unlink()  # a save cut short
    assert not TrainState.exists(tmp_path / "rolling")
    resumed, history = train_policy(
        tiny_policy(), _data(), None, cfg, progress=False, resume=TrainState.load(tmp_path / "at4")
    )
    assert state_equal(straight, resumed)
    assert history["step"][0] == 0  # the history before the checkpoint is kept


def test_finetuning_starts_from_the_parent_and_keeps_its_action_space(tmp_path):
    parent = tiny_policy()
    cfg = FinetuneConfig(steps=6, batch_size=8, checkpoint_every=3, warmup_steps=1)
    takeover = _data(10, 1)
    takeover[keys.OBS][:, 0, 3] = 40.0  # one dimension far outside the parent's observation range
    child, history = finetune_policy(parent, takeover, _data(30, 2), cfg, tmp_path / "work", progress=False)
    assert history["takeover_samples"] == 10 and history["pretraining_samples"] == 30
    assert child.action_normalizer.stats() == parent.action_normalizer.stats()
    # the observation range: widened to the takeover data where it lies outside, the parent's elsewhere
    assert history["obs_dims_widened"] >= 1
    assert child.obs_normalizer.stats()["max"][3] == pytest.approx(40.0)
    low, high = np.array(parent.obs_normalizer.stats()["min"]), np.array(parent.obs_normalizer.stats()["max"])
    inside = np.all((takeover[keys.OBS][:, 0] >= low) & (takeover[keys.OBS][:, 0] <= high), axis=0)
    for d in np.flatnonzero(inside):
        assert child.obs_normalizer.stats()["min"][d] == parent.obs_normalizer.stats()["min"][d]
        assert child.obs_normalizer.stats()["max"][d] == parent.obs_normalizer.stats()["max"][d]
    kept, history = finetune_policy(parent, takeover, _data(30, 2), replace(cfg, widen_obs_range=False), progress=False)
    assert kept.obs_normalizer.stats() == parent.obs_normalizer.stats() and history["obs_dims_widened"] == 0
    assert not state_equal(child, parent)
    assert TrainState.load(tmp_path / "work").step == 6
    with pytest.raises(FinetuneDataError, match="no takeover samples"):
        finetune_policy(parent, _data(0), _data(30), cfg, progress=False)


def _segment(path, obs_dim=26, steps=4, close=True):
    w = SegmentWriter(path, {"robot": 0})
    for t in range(steps):
        act = np.r_[[0.01 * t, 0, 0.9], [0, 1, 0, 1, 0, 0], [1.0]]
        w.write_step(np.full(obs_dim, t, np.float32), {}, act, act * 0, act[:3], [0, 0, 0, 1.0], None)
    if close:
        w.close("closed", "hand-back")
    else:
        w.flush()
    return path


def test_the_segment_reader_windows_each_segment_and_names_what_it_skips(tmp_path):
    a = _segment(tmp_path / "a.mcap", steps=3)
    b = _segment(tmp_path / "b.mcap", steps=2)
    wrong = _segment(tmp_path / "wrong.mcap", obs_dim=5)
    (tmp_path / "junk.mcap").write_bytes(b"junk")
    open_one = _segment(tmp_path / "open.mcap", close=False)
    out = load_takeovers([a, tmp_path / "junk.mcap", wrong, b, tmp_path / "missing.mcap", open_one], obs_dim=26)
    assert out.used == ["a.mcap", "b.mcap"] and len(out) == 5
    assert set(out.skipped) == {"junk.mcap", "wrong.mcap", "missing.mcap", "open.mcap"}
    assert "the policy takes 26" in out.skipped["wrong.mcap"] and out.skipped["missing.mcap"] == "no such file"
    arrays = out.arrays(obs_horizon=2, action_horizon=3)
    assert arrays[keys.OBS].shape == (5, 2, 26) and arrays[keys.ACTION].shape == (5, 3, 10)
    # segment a: history padded with its first observation, chunk with its last action; b starts fresh
    assert arrays[keys.OBS][0, :, 0].tolist() == [0, 0] and arrays[keys.OBS][1, :, 0].tolist() == [0, 1]
    assert arrays[keys.ACTION][2, :, 0].tolist() == pytest.approx([0.02, 0.02, 0.02])
    assert arrays[keys.OBS][3, :, 0].tolist() == [0, 0]
    # the label is the absolute action the operator's command produced, not the serving version's normalized one
    assert arrays[keys.ACTION][1, 0].tolist() == pytest.approx([0.01, 0, 0.9, 0, 1, 0, 1, 0, 0, 1])


def test_pretraining_episodes_of_another_observation_layout_are_refused_naming_them(tmp_path):
    import json

    from policy.checkpoint import load_policy
    from policy.finetune import pretraining_split
    from sim.registry import make_task
    from tests.helpers import finetunable_policy_folder

    labels = make_task("lift-cube").obs_spec.labels()
    folder = finetunable_policy_folder(tmp_path, "lift-cube", obs_labels=labels)
    policy, info = load_policy(folder)
    assert len(pretraining_split(policy, info, tmp_path / "demos").train_names) == 4
    # the same episodes, as if the task's observation had changed since the policy was trained
    moved = labels[:11] + labels[23:] + labels[11:23]
    config = folder / "config.json"
    config.write_text(json.dumps(json.loads(config.read_text()) | {"obs_labels": moved}))
    policy, info = load_policy(folder)
    with pytest.raises(FinetuneDataError) as err:
        pretraining_split(policy, info, tmp_path / "demos")
    message = str(err.value)
    assert message.startswith(f"5 episode(s) of {tmp_path / 'demos'} were recorded with another observation layout")
    assert "lift-cube_seed000000.mcap: recorded with another observation layout ([eef_pos(3)" in message
    assert "the same channels in another order (at channel 11: object_pos, not object_extent)" in message
    assert message.endswith("; and 2 more")  # three named, the rest counted

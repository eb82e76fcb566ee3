"""The one control step: chunk queues, per-robot noise, asking, takeovers and hand-back."""

import numpy as np
import pytest
import torch

from policy.config import DiffusionPolicyConfig
from policy.controller import Controller, ControllerConfig, Mode
from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import Scores
from sim.frame import RobotFrame
from sim.spaces import TeleopCommand
from sim.tasks.lift import LIFT_OBS
from storage import keys
from tests.helpers import KinematicTask, tiny_policy


class Scripted:
    """A hand-made signal: asks when told to, and under teleop wants help until told otherwise."""

    name = "scripted"
    calibration = {"threshold": 0.5}
    threshold = 0.5

    def __init__(self):
        self.ask, self.keep, self.now = set(), set(), set()
        self.seen_teleop = []

    def reset(self, robot_ids=None):
        pass

    def score(self, batch):
        return Scores(np.array([float(i in self.ask) for i in batch.robot_ids]))

    def wants_help(self, scores, state):
        self.seen_teleop.append(state.teleop.copy())
        pairs = zip(state.robot_ids, state.teleop, strict=True)
        return np.array([(rid in self.keep) if tele else (rid in self.ask) for rid, tele in pairs])

    def explain(self, scores, j):
        return f"told to ({scores.value[j]:.0f})"

    def urgent(self, state):
        return np.array([rid in self.now for rid in state.robot_ids])


def _chunked(horizon=4, steps=2, history=1):
    torch.manual_seed(0)
    p = DiffusionPolicy(
        DiffusionPolicyConfig(
            obs_dim=LIFT_OBS.dim,
            obs_horizon=history,
            action_horizon=horizon,
            n_action_steps=steps,
            network="mlp",
            mlp_hidden=16,
            step_embed_dim=8,
            num_inference_steps=2,
        )
    )
    p.fit_normalizers(
        np.random.default_rng(0).normal(size=(64, LIFT_OBS.dim)), np.random.default_rng(1).uniform(size=(64, 10))
    )
    return p.eval()


def _frames(tasks, results=None):
    return {rid: RobotFrame.from_task(t, None if results is None else results[rid]) for rid, t in tasks.items()}


def _run(controller, tasks, steps, commands=None):
    """Steps every robot ``steps`` times; returns each robot's list of RobotSteps."""
    frames = _frames(tasks)
    out = {rid: [] for rid in tasks}
    for _ in range(steps):
        decided = controller.step(frames, commands(controller) if commands else None)
        results = {}
        for rid, st in decided.items():
            out[rid].append(st)
            results[rid] = tasks[rid].step(st.action)
        frames = _frames(tasks, results)
    return out


def _tasks(seeds):
    tasks = {}
    for rid, seed in seeds.items():
        tasks[rid] = KinematicTask()
        tasks[rid].reset(seed)
    return tasks


def test_a_chunk_is_queued_and_executed_as_trained():
    policy = _chunked(horizon=4, steps=2)
    calls = []
    sample = policy.predict_action_chunk

    def counting(obs, generator=None, noise=None):
        calls.append(obs.shape[0])
        return sample(obs, generator, noise)

    policy.predict_action_chunk = counting
    controller = Controller(policy, {}, None, KinematicTask().action_space)
    controller.reset(0, seed=3)
    steps = _run(controller, _tasks({0: 3}), 6)[0]
    assert len(calls) == 3  # one chunk per n_action_steps = 2 steps, not one per step
    assert all(s.source == keys.SOURCE_POLICY for s in steps)
    # the executed pairs are the first two actions of one chunk, sampled from this robot's noise
    controller.reset(0, seed=3)
    first = controller._robots[0].generator  # noqa: SLF001 - compare with the same seeded draw
    noise = torch.randn((4, 10), generator=first)
    obs = torch.as_tensor(steps[0].obs)[None]
    chunk = sample(obs, noise=noise[None])[0].numpy()
    np.testing.assert_allclose(steps[0].action, chunk[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(steps[1].action, chunk[1], rtol=1e-5, atol=1e-6)


def test_actions_depend_on_the_episode_seed_not_on_the_batch():
    policy = tiny_policy()
    space = KinematicTask().action_space
    alone = Controller(policy, {}, None, space)
    alone.reset(7, seed=11)
    solo = _run(alone, _tasks({7: 11}), 5)[7]
    crowd = Controller(policy, {}, None, space)
    for rid, seed in {1: 5, 7: 11, 9: 2}.items():
        crowd.reset(rid, seed)
    together = _run(crowd, _tasks({1: 5, 7: 11, 9: 2}), 5)
    for a, b in zip(solo, together[7], strict=True):
        np.testing.assert_allclose(a.action, b.action, rtol=1e-5, atol=1e-6)
    assert not np.allclose(together[1][0].action, together[7][0].action)


def test_asking_holding_a_budgeted_takeover_and_a_fresh_history_on_hand_back():
    policy, signal = tiny_policy(), Scripted()
    controller = Controller(
        policy, {"scripted": signal}, "scripted", KinematicTask().action_space, ControllerConfig(budget=2)
    )
    controller.reset(0, seed=1)
    tasks = _tasks({0: 1})
    signal.ask.add(0)
    frames = _frames(tasks)
    asked = controller.step(frames)[0]
    assert asked.asked and asked.source == keys.SOURCE_HOLD and asked.mode == Mode.WAITING
    assert asked.asked_by == "scripted" and asked.why == "told to (1)"  # the signal's words, for the queue
    np.testing.assert_allclose(asked.action, frames[0].hold)
    held = controller.step(frames)[0]  # nobody has claimed it: it holds, unscored
    assert held.source == keys.SOURCE_HOLD and not held.scores
    signal.ask.clear()
    controller.take_over(0)
    up = TeleopCommand((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), 1.0)
    first = controller.step(frames, {0: up})[0]
    assert first.source == keys.SOURCE_OPERATOR and not first.returned and first.mode == Mode.TELEOP
    np.testing.assert_allclose(first.action[:3], frames[0].pos + [0, 0, 0.01])
    assert first.action[9] == 1.0 and first.scores  # scored in shadow, for the segment and switch-back
    idle = controller.step(frames)[0]  # teleop without a command: holds the operator's last target
    np.testing.assert_allclose(idle.action, first.action)
    second = controller.step(frames, {0: up})[0]
    assert second.returned and second.mode == Mode.AUTONOMOUS  # budget of 2 operator steps
    with pytest.raises(ValueError, match="not under teleop"):
        controller.step(frames, {0: up})
    back = controller.step(frames)[0]
    assert back.source == keys.SOURCE_POLICY
    assert back.obs.shape == (1, LIFT_OBS.dim) and np.allclose(back.obs[0], frames[0].obs)  # a fresh history
    assert any(t.any() for t in signal.seen_teleop)  # the trigger rule saw the teleop flags


@pytest.mark.parametrize("resume", ["restart", "history"])
def test_after_a_hand_back_the_history_restarts_or_keeps_the_takeovers_frames(resume):
    """A policy that sees 2 frames: on a plain restart both are the frame it resumes on; with
    ``resume = "history"`` the first is the frame of the operator's last step, so it sees the motion."""
    policy, signal = _chunked(horizon=4, steps=2, history=2), Scripted()
    config = ControllerConfig(budget=2, resume=resume)
    controller = Controller(policy, {"scripted": signal}, "scripted", KinematicTask().action_space, config)
    controller.reset(0, seed=1)
    tasks = _tasks({0: 1})
    frames = _frames(tasks)
    controller.ask(0, frames[0].hold)
    controller.take_over(0)
    up = TeleopCommand((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), 1.0)
    seen = []
    for _ in range(2):  # the budget: two operator steps, each moving the robot up 1 cm
        step = controller.step(frames, {0: up})[0]
        seen.append(frames[0].obs)
        frames = _frames(tasks, {0: tasks[0].step(step.action)})
    assert step.returned
    back = controller.step(frames)[0]
    assert back.source == keys.SOURCE_POLICY and back.obs.shape == (2, LIFT_OBS.dim)
    np.testing.assert_allclose(back.obs[1], frames[0].obs)
    np.testing.assert_allclose(back.obs[0], frames[0].obs if resume == "restart" else seen[-1])
    assert not np.allclose(seen[-1], frames[0].obs)  # the operator's step moved the robot
    with pytest.raises(ValueError, match="resume"):
        ControllerConfig(resume="rewind")


@pytest.mark.parametrize("return_after", [None, 1])
def test_continuous_mode_returns_control_when_the_operator_or_the_switch_back_rule_says_so(return_after):
    policy, signal = tiny_policy(), Scripted()
    config = ControllerConfig(hand_back="continuous", return_after=return_after, cooldown=2)
    controller = Controller(policy, {"scripted": signal}, "scripted", KinematicTask().action_space, config)
    controller.reset(4, seed=1)
    frames = _frames(_tasks({4: 1}))
    controller.ask(4, frames[4].hold)
    controller.take_over(4)
    signal.keep.add(4)  # the operator's help is still wanted
    cmd = TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), -1.0)
    for _ in range(3):
        assert not controller.step(frames, {4: cmd})[4].returned
    signal.keep.clear()  # the rule says the policy can take over again
    st = controller.step(frames, {4: cmd})[4]
    if return_after is None:  # only the operator hands back
        assert not st.returned and controller.mode(4) == Mode.TELEOP
        controller.release(4)
    else:
        assert st.returned
    assert controller.mode(4) == Mode.AUTONOMOUS
    signal.ask.add(4)  # it wants help again at once: the cooldown holds the request back two steps
    assert [controller.step(frames)[4].asked for _ in range(3)] == [False, False, True]


def test_an_urgent_request_is_not_held_back_by_the_cooldown():
    policy, signal = tiny_policy(), Scripted()
    config = ControllerConfig(budget=1, cooldown=5)
    controller = Controller(policy, {"scripted": signal}, "scripted", KinematicTask().action_space, config)
    controller.reset(0, seed=1)
    frames = _frames(_tasks({0: 1}))
    controller.ask(0, frames[0].hold)
    controller.take_over(0)
    assert controller.step(frames, {0: TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0)})[0].returned
    signal.ask.add(0)
    assert not controller.step(frames)[0].asked  # the cooldown holds an ordinary request back
    signal.now.add(0)  # the policy's next step would undo the operator's work
    st = controller.step(frames)[0]
    assert st.asked and st.asked_by == "scripted" and st.source == keys.SOURCE_HOLD
    signal.now.clear()
    controller.release(0)
    assert not controller.step(frames)[0].asked
    shadow = Controller(
        policy, {"scripted": signal}, "scripted", KinematicTask().action_space, ControllerConfig(assistance=False)
    )
    shadow.reset(0, seed=1)
    signal.now.add(0)
    assert not shadow.step(frames)[0].asked  # a shadow run never asks, urgent or not


def test_a_shadow_run_scores_but_never_asks():
    policy, signal = tiny_policy(), Scripted()
    controller = Controller(
        policy, {"scripted": signal}, "scripted", KinematicTask().action_space, ControllerConfig(assistance=False)
    )
    controller.reset(0, seed=1)
    signal.ask.add(0)
    steps = _run(controller, _tasks({0: 1}), 3)[0]
    assert all(s.source == keys.SOURCE_POLICY and s.wants["scripted"] and not s.asked for s in steps)


def test_the_asking_signal_must_be_calibrated():
    from policy.signals import SignalError, make_signal

    policy = tiny_policy()
    with pytest.raises(SignalError, match="not calibrated"):
        Controller(policy, {"denoising": make_signal("denoising", policy)}, "denoising", KinematicTask().action_space)


def test_the_hand_back_rule_has_one_vocabulary():
    """``ControllerConfig`` names and checks the controller's settings; the assisted rollouts' config builds it,
    with the same names; the old alias ``calm_steps`` is gone (``return_after``)."""
    from dataclasses import fields

    from lab.assisted import AssistConfig

    assert {f.name for f in fields(AssistConfig)} >= set(ControllerConfig.model_fields) - {
        "assistance"
    }  # no driver: none
    assert not hasattr(ControllerConfig(), "calm_steps") and not hasattr(AssistConfig(), "mode")
    assert AssistConfig(hand_back="continuous", budget=7).controller_config().budget == 7
    assert AssistConfig(hand_back="continuous").hand_back == "continuous"
    with pytest.raises(ValueError, match="hand_back"):
        AssistConfig(hand_back="sometimes")

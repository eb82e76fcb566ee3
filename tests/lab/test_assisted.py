import numpy as np

from lab.assisted import AssistConfig, run_assisted, summarize_assisted
from policy.signals import make_signal
from policy.signals.base import Scores, TriggerState
from sim.registry import make_expert
from sim.spaces import TeleopCommand
from tests.helpers import tiny_policy


class _Every:
    """Asks on a fixed schedule: a hand-made driver to check the takeover bookkeeping."""

    name = "schedule"
    calibration = {"threshold": 0.5}
    threshold = 0.5

    def __init__(self, period):
        self.period = period
        self.t = {}

    def reset(self, robot_ids=None):
        self.t = {}

    def score(self, batch):
        return Scores(np.zeros(len(batch)))

    def wants_help(self, scores, state):
        out = []
        for rid in state.robot_ids:
            self.t[int(rid)] = self.t.get(int(rid), -1) + 1
            out.append(self.t[int(rid)] % self.period == 0)
        return np.array(out)


def test_budgeted_takeovers_last_the_budget_and_shadow_signals_score_every_step():
    policy = tiny_policy()
    shadow = {"denoising": make_signal("denoising", policy, {"num_samples": 16, "max_modes": 2})}
    shadow["denoising"].calibration = {"threshold": 1e9}
    cfg = AssistConfig(hand_back="budgeted", budget=3, n_envs=2)
    episodes, _ = run_assisted(policy, "lift-cube", [5, 6], _Every(10), shadow, cfg, progress=False)
    for ep in episodes:
        assert len(ep.operator) == len(ep.scores["denoising"]) == ep.steps
        # every step is scored, the step on which the robot asks (and holds) included
        assert np.isfinite(ep.scores["denoising"]).all() and ep.events > 0
        # every takeover is exactly `budget` operator steps, then the policy is back
        runs = np.diff(np.flatnonzero(np.diff(np.r_[0, np.asarray(ep.operator, int), 0])))[::2]
        assert ep.events == len(runs) and (runs == 3).all() or ep.success
    summary = summarize_assisted(episodes)
    assert summary["help_rate"]["denoising"] == 0.0  # threshold never crossed in shadow


def test_full_teleop_in_continuous_mode_lets_the_operator_finish_the_task():
    policy = tiny_policy()
    driver = make_signal("full-teleop", policy)
    episodes, _ = run_assisted(
        policy, "lift-cube", [7], driver, {}, AssistConfig(hand_back="continuous", n_envs=1), progress=False
    )
    ep = episodes[0]
    # the robot asks at its first step (and holds), then the operator drives to the end
    assert ep.success and ep.events == 1 and not ep.operator[0] and all(ep.operator[1:])
    assert ep.asked_at == [0] and ep.summary()["asked_at"] == [0]
    assert TriggerState([1]).teleop.tolist() == [False]


def test_an_operator_taking_over_picks_up_where_the_scene_stands(task_cache):

    task = task_cache("lift-cube")
    task.reset(3)
    fresh = make_expert("lift-cube")
    fresh.resume(task, np.random.default_rng(0))
    assert fresh.phase == "approach"  # nothing done yet
    expert = make_expert("lift-cube")
    expert.reset(task, np.random.default_rng(1))
    for _ in range(200):
        if expert.phase == "lift" and task.privileged()["object_pos"][2] > task.privileged()["rest_z"] + 0.02:
            break
        task.step(task.teleop(expert.act(task)).action)
    else:
        raise AssertionError("the expert did not get the cube off the table")
    late = make_expert("lift-cube")
    late.resume(task, np.random.default_rng(2))
    assert late.phase == "lift"  # keeps holding and lifts, instead of opening to start over


def test_a_takeover_just_above_the_grasp_goes_across_and_down_without_climbing(task_cache):
    """A robot that stopped 3 cm above and 2.5 cm beside the grasp: the operator's plan no longer
    climbs to its 5-14 cm approach height first (each of its steps stays at or under the height it
    started from), and it reaches the grasp sooner than an operator planning from the approach height."""
    task = task_cache("lift-cube")

    def stand_near(seed: int) -> float:
        task.reset(seed)
        grasp = task.privileged()["grasp_point"]
        target = grasp + np.array([0.025, 0.0, 0.03])
        for _ in range(60):  # drive there with the gripper open, as a stalled policy would have
            pos = task.ee_pose()[0]
            if np.linalg.norm(pos - target) < 0.004:
                break
            task.step(task.teleop(TeleopCommand(tuple(np.clip(target - pos, -0.02, 0.02)), (0, 0, 0), -1.0)).action)
        return float(task.ee_pose()[0][2])

    def steps_to_grasp(expert) -> tuple[int, float]:
        top = -np.inf
        for k in range(150):
            if expert.phase == "close":
                return k, top
            task.step(task.teleop(expert.act(task)).action)
            top = max(top, float(task.ee_pose()[0][2]))
        raise AssertionError("the operator never reached the grasp")

    start = stand_near(5)
    near = make_expert("lift-cube")
    near.resume(task, np.random.default_rng(0))
    steps, top = steps_to_grasp(near)
    assert top < start + 0.005
    stand_near(5)
    planned = make_expert("lift-cube")  # the same plan from its approach height (2.5 cm beside: "approach")
    planned.reset(task, np.random.default_rng(0))
    assert steps < steps_to_grasp(planned)[0]


def test_an_operator_who_hands_back_when_held_gives_the_robot_back_holding_the_object(task_cache):
    from lab.assisted import ExpertOperator
    from sim.frame import RobotFrame

    task = task_cache("lift-cube")
    task.reset(3)
    operator = ExpertOperator("lift-cube", [3], hands_back_when_held=True)
    frame = RobotFrame.from_task(task)
    operator.take_over(0, frame)
    steps = 0
    while not operator.hands_back(0, frame):
        assert steps < 200, "the operator never handed back"
        result = task.step(task.teleop(operator.command(0, frame)).action)
        frame = RobotFrame.from_task(task, result)
        steps += 1
    s = task.privileged()
    assert task.gripper_opening() < 0.07 and s["object_pos"][2] > s["rest_z"] + 0.01 and steps > 10
    # asked again while the object is held, it does not hand straight back; the default operator never does
    operator.take_over(0, frame)
    assert not operator.hands_back(0, frame)
    keeps = ExpertOperator("lift-cube", [3])
    keeps.take_over(0, frame)
    assert not keeps.hands_back(0, frame)


def test_operator_hand_back_in_a_rollout_returns_control_once():
    policy = tiny_policy()
    cfg = AssistConfig(hand_back="continuous", return_after=None, operator_hands_back=True, n_envs=1)
    episodes, _ = run_assisted(policy, "lift-cube", [3], _Every(10_000), {}, cfg, progress=False)
    ep = episodes[0]
    flags = np.asarray(ep.operator, int)
    starts = np.flatnonzero(np.diff(np.r_[0, flags]) == 1)
    # asked at the first step, one takeover, then the policy drives the rest of the episode
    assert ep.events == 1 and ep.asked_at == [0] and len(starts) == 1 and starts[0] == 1
    assert 10 < flags.sum() < ep.steps - 1 and not flags[-1]
    assert ep.actions[flags.sum()][-1] > 0  # the operator's last action keeps the gripper closed


def test_assist_config_refuses_a_continuous_mode_nothing_hands_back():
    import pytest

    with pytest.raises(ValueError, match="nothing hands back"):
        AssistConfig(hand_back="continuous", return_after=None)
    with pytest.raises(ValueError, match="return_after"):
        AssistConfig(return_after=0)

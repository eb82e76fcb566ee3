"""Assisted rollouts: a driver signal decides when the simulated operator (the task's scripted
expert) takes over; every other signal runs in shadow on the same trajectory.

The episodes run through the fleet's ``Controller`` (``policy.lockstep``), so a robot that asks
holds for one step, exactly as a served robot does while its operator claims it, and is then
driven by the operator. At each takeover the operator picks up where the scene stands
(``Expert.resume``: an object already held is lifted, not dropped to start over). Every signal
scores every robot the policy or the operator moves (under teleop, the policy's would-be chunk
feeds switch-back rules); the driver's ``wants_help`` (with the teleop flags) starts or ends
takeovers.

Modes, as in the paper: ``budgeted`` gives the operator ``budget`` steps per assistance event;
``continuous`` keeps the operator in control until the driver no longer wants help (for
``thrifty`` this is its switch-back rule; for the others the score back under the threshold): the
controller's ``continuous`` with ``return_after = 1`` (``AssistConfig.return_after``: more calm steps
keep the operator in control longer), since by default the simulated operator never hands back on
its own. With ``operator_hands_back`` it does, once the object it was asked about is held
(``Expert.holding``), as an operator who was called for a grasp would, or, with
``operator_hands_back_at = "placed"``, once the gripper stands open at the grasp (``Expert.placed``); with
``return_after = None`` that is the only hand-back. On hand-back the policy restarts from the current pose with a fresh
observation history.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from policy.controller import Controller, ControllerConfig, RobotStep
from policy.diffusion_policy import DiffusionPolicy
from policy.lockstep import ResetHook, run_lockstep
from policy.signals.base import AssistanceSignal
from sim.env import Task
from sim.experts import OperatorStyle
from sim.frame import RobotFrame
from sim.registry import make_expert, make_task
from sim.spaces import TeleopCommand, TeleopLimits
from sim.view import OperatorView
from storage import keys

LIMITS = TeleopLimits()
# where the simulated operator hands back on its own (``ExpertOperator``): once the object is held, or once
# the gripper stands open at the grasp (the pre-grasp pose)
HANDS_BACK_AT = ("held", "placed")


@dataclass(frozen=True)
class AssistConfig:
    hand_back: str = "budgeted"  # the controller's names (``policy.hand_back.ControllerConfig``)
    budget: int = 4  # operator steps per assistance event (budgeted mode)
    cooldown: int = 0  # policy steps after a hand-back on which the robot does not ask again
    resume: str = "restart"  # what the policy sees first after a hand-back (``policy.hand_back.RESUME``)
    watchdog: float | None = None  # ask once at this fraction of the horizon without success
    n_envs: int = 4
    seed: int = 0
    batch_invariant: bool = False  # the controller's robot-by-robot mode (to compare with the service)
    # continuous mode: hand back after this many calm operator steps (the paper's: 1; None: only the operator)
    return_after: int | None = 1
    # the simulated operator hands back once the scene shows the object held (``Expert.holding``), as a
    # console operator asked to help with a grasp does
    operator_hands_back: bool = False
    operator_hands_back_at: str = "held"  # one of HANDS_BACK_AT
    # how the simulated operator plans at a takeover after the policy moved the robot (``sim.experts.OperatorStyle``)
    operator: str = OperatorStyle.CARRY_ON

    def controller_config(self) -> ControllerConfig:
        """The controller's settings of these rollouts (ValidationError naming a bad one)."""
        return ControllerConfig(
            hand_back=self.hand_back,
            budget=self.budget,
            return_after=self.return_after if self.hand_back == "continuous" else None,
            cooldown=self.cooldown,
            resume=self.resume,
            watchdog=self.watchdog,
            batch_invariant=self.batch_invariant,
        )

    def __post_init__(self) -> None:
        if self.operator not in tuple(OperatorStyle):
            raise ValueError(f"operator must be one of {[str(s) for s in OperatorStyle]}, got {self.operator!r}")
        if self.operator_hands_back_at not in HANDS_BACK_AT:
            at = self.operator_hands_back_at
            raise ValueError(f"operator_hands_back_at must be one of {HANDS_BACK_AT}, got {at!r}")
        if not (isinstance(self.n_envs, int) and self.n_envs >= 1):
            raise ValueError(f"n_envs must be an integer >= 1, got {self.n_envs!r}")
        self.controller_config()  # the controller's settings, checked where they are declared
        ControllerConfig(return_after=self.return_after)  # also where budgeted rollouts leave it unused
        if self.return_after is None and self.hand_back == "continuous" and not self.operator_hands_back:
            raise ValueError("continuous mode with return_after None needs operator_hands_back: nothing hands back")


@dataclass
class AssistedEpisode:
    task: str
    seed: int
    driver: str
    success: bool = False
    steps: int = 0
    operator: list[bool] = field(default_factory=list)  # who executed each step
    actions: list[np.ndarray] = field(default_factory=list)  # the action sent at each step (10,)
    policy_in_control: list[bool] = field(default_factory=list)  # before each step's decision
    events: int = 0  # assistance requests by the driver
    asked_at: list[int] = field(default_factory=list)  # the steps (from 0) on which the robot asked
    scores: dict[str, list[float]] = field(default_factory=dict)  # every signal, every step
    wants: dict[str, list[bool]] = field(default_factory=dict)
    # the operator's steps as fine-tuning data: (observation (obs_dim,), absolute action (10,)), in order
    takeover_pairs: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    @property
    def assisted_steps(self) -> int:
        return int(sum(self.operator))

    def summary(self) -> dict:
        return {
            "seed": self.seed,
            "success": self.success,
            "steps": self.steps,
            "assisted_steps": self.assisted_steps,
            "events": self.events,
            "asked_at": self.asked_at,
        }


class ExpertOperator:
    """The task's scripted expert as the simulated operator, driving from the operator view only
    (``OperatorView``: pose, gripper and the scene, as ``hitl operator-bot`` sees them through the
    API). At each takeover it picks up where the scene stands (``Expert.take_over``: in the default
    ``carry-on`` style with one plan per episode, in ``replan`` style afresh at each request); its
    commands are clamped to the teleop limits, as a console's are. With ``hands_back_when_held`` it
    hands the robot back once the object, not held when it took over, is held (``Expert.holding``): it
    was asked for help, it gave the grasp. With ``at = "placed"`` it hands back earlier, once its plan has
    placed the open gripper at the grasp (``Expert.placed``): the policy is to close and lift."""

    def __init__(
        self,
        task_name: str,
        seeds: list[int],
        hands_back_when_held: bool = False,
        style: OperatorStyle | str = OperatorStyle.CARRY_ON,
        at: str = "held",
    ) -> None:
        if at not in HANDS_BACK_AT:
            raise ValueError(f"at must be one of {HANDS_BACK_AT}, got {at!r}")
        self.task_name, self.seeds = task_name, seeds
        self.hands_back_when_held, self.at = hands_back_when_held, at
        self.style = OperatorStyle(style)
        self.experts: dict[int, object] = {}
        self.events: dict[int, int] = {}
        self.clock: dict[int, int] = {}  # the robot's step clock after this operator's last command
        self.held_at_start: dict[int, bool] = {}

    def take_over(self, robot_id: int, frame: RobotFrame) -> None:
        """Plans from the view, or carries on with its plan when the policy has not moved the robot
        since this operator's last command (only hold steps in between: the clock has not moved)."""
        self.events[robot_id] = self.events.get(robot_id, 0) + 1
        expert = self.experts.setdefault(robot_id, make_expert(self.task_name, retry=True, style=self.style))
        view = OperatorView.from_frame(self.task_name, frame)
        carry_on = self.clock.get(robot_id) == frame.clock
        expert.take_over(view, self.seeds[robot_id], self.events[robot_id], carry_on)
        self.held_at_start[robot_id] = expert.holding(view)

    def hands_back(self, robot_id: int, frame: RobotFrame) -> bool:
        """Whether this operator gives the robot back now (before commanding this frame)."""
        if not self.hands_back_when_held or self.held_at_start.get(robot_id, True):
            return False
        view = OperatorView.from_frame(self.task_name, frame)
        expert = self.experts[robot_id]
        return expert.placed(view) if self.at == "placed" else expert.holding(view)

    def command(self, robot_id: int, frame: RobotFrame) -> TeleopCommand:
        self.clock[robot_id] = frame.clock + 1
        return self.experts[robot_id].act(OperatorView.from_frame(self.task_name, frame)).clamped(LIMITS)


def run_assisted(
    policy: DiffusionPolicy,
    task_name: str,
    seeds: list[int],
    driver: AssistanceSignal | None,
    shadow: dict[str, AssistanceSignal] | None = None,
    config: AssistConfig | None = None,
    progress: bool = True,
    on_reset: ResetHook | None = None,
) -> tuple[list[AssistedEpisode], dict]:
    """One assisted episode per seed, in waves of ``n_envs`` robots stepping in lockstep through the
    fleet's ``Controller``: a robot that asks holds for one step while the simulated operator takes
    over, then the operator's commands drive it until control returns. With no ``driver`` nothing
    asks: the policy runs alone and every ``shadow`` signal is scored (autonomous shadow runs).
    on_reset: told each robot's task at the start of its episode (a benchmark's privileged probe,
    ``bench.oracle``)."""
    cfg = config or AssistConfig()
    driver_name = driver.name if driver is not None else None
    shadow = {k: v for k, v in (shadow or {}).items() if k != driver_name}
    signals = {**({driver_name: driver} if driver is not None else {}), **shadow}
    controller = Controller(
        policy,
        signals,
        driver_name,
        make_task(task_name).action_space,
        cfg.controller_config(),
        seed=cfg.seed,
    )
    episodes = [
        AssistedEpisode(
            task_name, s, driver_name or "none", scores={k: [] for k in signals}, wants={k: [] for k in signals}
        )
        for s in seeds
    ]

    def record(rid: int, task: Task, step: RobotStep) -> None:
        ep = episodes[rid]
        ep.operator.append(step.source == keys.SOURCE_OPERATOR)
        ep.actions.append(step.action)
        if step.source == keys.SOURCE_OPERATOR:  # called before the step: the observation it acted on
            ep.takeover_pairs.append((task.observation().astype(np.float32), np.asarray(step.action, np.float32)))
        ep.policy_in_control.append(step.source == keys.SOURCE_POLICY or step.asked)
        if step.asked:
            ep.asked_at.append(len(ep.operator) - 1)
        ep.events += int(step.asked)
        for name in signals:  # NaN / False on the hold step while the operator takes over (not scored)
            ep.scores[name].append(step.scores.get(name, float("nan")))
            ep.wants[name].append(step.wants.get(name, False))

    start = time.perf_counter()
    with torch.no_grad():
        outcomes = run_lockstep(
            controller,
            task_name,
            seeds,
            cfg.n_envs,
            record,
            ExpertOperator(
                task_name,
                seeds,
                hands_back_when_held=cfg.operator_hands_back,
                style=cfg.operator,
                at=cfg.operator_hands_back_at,
            ),
            progress,
            f"assisted {task_name} ({driver_name})" if driver is not None else f"shadow {task_name}",
            on_reset=on_reset,
        )
    for ep, out in zip(episodes, outcomes, strict=True):
        ep.success, ep.steps = out.success, out.steps
    return episodes, {"seconds": time.perf_counter() - start}


def summarize_assisted(episodes: list[AssistedEpisode]) -> dict:
    """Success, assisted steps and events per episode, and each signal's help rate on the steps where
    the policy was in control when the decision was taken (the rate to match a ``random`` reference to)."""
    auto = np.concatenate([np.asarray(e.policy_in_control, dtype=bool) for e in episodes])
    out = {
        "episodes": len(episodes),
        "driver": episodes[0].driver if episodes else None,
        "success_rate": float(np.mean([e.success for e in episodes])) if episodes else 0.0,
        "assisted_steps_per_episode": float(np.mean([e.assisted_steps for e in episodes])) if episodes else 0.0,
        "events_per_episode": float(np.mean([e.events for e in episodes])) if episodes else 0.0,
        "steps_per_episode": float(np.mean([e.steps for e in episodes])) if episodes else 0.0,
        "help_rate": {},
    }
    for name in episodes[0].wants if episodes else []:
        wants = np.concatenate([np.asarray(e.wants[name], dtype=bool) for e in episodes])
        out["help_rate"][name] = float(wants[auto].mean()) if auto.any() else None
    return out

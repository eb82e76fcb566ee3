"""In-process simulated robots stepping in lockstep around the one ``Controller``.

The product keeps it: the fine-tuning job evaluates and fits its candidates on these rollouts
(``policy.evaluate``, ``policy.finetune``), and the operator bot gives up at its ``OVERTIME``.
Autonomous evaluation and the lab's assisted rollouts (``lab.assisted``, which passes the simulated
operator) both run their episodes here, in waves of ``n_envs`` robots: each step builds every live
robot's ``RobotFrame``, asks the simulated operator (if any) for commands for the robots it drives,
calls ``Controller.step`` once for the whole wave, and applies the actions. Robot ids are the
episodes' indices in ``seeds``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from tqdm import tqdm

from policy.controller import Controller, Mode, RobotStep, ends_episode
from sim.env import StepResult, Task
from sim.frame import RobotFrame
from sim.registry import make_task
from sim.spaces import TeleopCommand
from storage import keys

OVERTIME = 2  # an episode's hard stop, in horizons of control steps (holds and overtime under teleop)


class SimulatedOperator(Protocol):
    """Answers assistance requests from what an operator sees of the robot: its frame (pose, gripper
    and the scene's goal, ``sim.view.OperatorView``), never the simulator's hidden state."""

    def take_over(self, robot_id: int, frame: RobotFrame) -> None: ...

    def command(self, robot_id: int, frame: RobotFrame) -> TeleopCommand: ...

    def hands_back(self, robot_id: int, frame: RobotFrame) -> bool:
        """Whether the operator gives a robot it drives back to the policy now, before commanding ``frame``."""
        ...


@dataclass
class Outcome:
    seed: int
    success: bool = False
    steps: int = 0
    info: dict = field(default_factory=dict)


# called for every robot and step before the action is applied: (robot id, task, the decision)
StepHook = Callable[[int, Task, RobotStep], None]
# called for every robot once its episode's task is reset, before its first step: (robot id, task)
ResetHook = Callable[[int, Task], None]


def run_lockstep(
    controller: Controller,
    task_name: str,
    seeds: list[int],
    n_envs: int,
    on_step: StepHook | None = None,
    operator: SimulatedOperator | None = None,
    progress: bool = True,
    desc: str = "",
    on_reset: ResetHook | None = None,
) -> list[Outcome]:
    """One episode per seed; an episode ends as the fleet's do (``ends_episode``): at success or at the
    task's horizon (hold steps do not count), a timeout waiting for the operator's hand-back. The
    simulated operator never leaves, so unlike the fleet (where an unclaimed request or an operator who
    keeps control holds an episode open), an episode here also stops after ``OVERTIME`` horizons of
    control steps."""
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs}")
    sees = bool(controller.policy.config.cameras)  # a policy that sees cameras runs the task as it observes it
    tasks = [make_task(task_name, images=sees) for _ in range(min(n_envs, len(seeds)))]
    obs_dim = tasks[0].obs_spec.dim
    if obs_dim != controller.policy.config.obs_dim:
        raise ValueError(
            f"policy expects {controller.policy.config.obs_dim}-dim observations, task {task_name} gives {obs_dim}"
        )
    outcomes = [Outcome(s) for s in seeds]
    bar = tqdm(total=len(seeds), desc=desc or task_name, disable=not progress, unit="ep")
    try:
        for w in range(0, len(seeds), len(tasks)):
            wave = {w + j: task for j, task in enumerate(tasks[: len(seeds) - w])}
            frames: dict[int, RobotFrame] = {}
            for rid, task in wave.items():
                task.reset(seeds[rid])
                controller.reset(rid, seeds[rid])
                if on_reset is not None:
                    on_reset(rid, task)
                frames[rid] = RobotFrame.from_task(task)
            while frames:
                commands = {}
                if operator is not None:
                    for rid in frames:
                        mode = controller.mode(rid)
                        if mode == Mode.WAITING:  # the simulated operator answers at once
                            controller.take_over(rid)
                            operator.take_over(rid, frames[rid])
                        elif mode == Mode.TELEOP and operator.hands_back(rid, frames[rid]):
                            controller.release(rid)  # the policy acts on this frame
                            continue
                        if mode != Mode.AUTONOMOUS:
                            commands[rid] = operator.command(rid, frames[rid])
                steps = controller.step(frames, commands)
                frames = {}
                for rid, step in steps.items():
                    task = wave[rid]
                    if on_step is not None:
                        on_step(rid, task, step)
                    result: StepResult = task.step(step.action, hold=step.source == keys.SOURCE_HOLD)
                    out = outcomes[rid]
                    out.steps = result.t
                    frame = RobotFrame.from_task(task, result)
                    if ends_episode(frame, controller.mode(rid)) or result.t >= OVERTIME * task.horizon:
                        out.success, out.info = bool(result.success), task.episode_info()
                        controller.remove(rid)
                        bar.update(1)
                    else:
                        frames[rid] = frame
    finally:
        bar.close()
        for t in tasks:
            t.close()
    return outcomes

"""The task registry: ``make_task(name)`` and the matching scripted expert."""

from __future__ import annotations

from collections.abc import Callable

from sim.env import Task
from sim.experts import CupStackExpert, Expert, LiftExpert, OpenDrawerExpert, OperatorStyle
from sim.tasks.cup_stack import CupStackTask
from sim.tasks.lift import LiftTask
from sim.tasks.open_drawer import OpenDrawerTask

TASKS: dict[str, Callable[[], Task]] = {
    "lift-cube": lambda: LiftTask("cube"),
    "lift-nut": lambda: LiftTask("nut"),
    "lift-hammer": lambda: LiftTask("hammer"),
    "lift-hook": lambda: LiftTask("hook"),
    "cup-stack": CupStackTask,
    "open-drawer": OpenDrawerTask,
}

EXPERTS: dict[str, Callable[[], Expert]] = {
    "lift-cube": LiftExpert,
    "lift-nut": LiftExpert,
    "lift-hammer": LiftExpert,
    "lift-hook": LiftExpert,
    "cup-stack": CupStackExpert,
    "open-drawer": OpenDrawerExpert,
}


def _check(name: str) -> None:
    if name not in TASKS:
        raise KeyError(f"unknown task {name!r}; registered tasks: {', '.join(TASKS)}")


def make_task(name: str, images: bool = False) -> Task:
    """The task ``name``; ``images``: as a policy that sees cameras observes it (``Task.see_cameras``): its
    frames carry what its cameras see (``Task.cameras``) and its observation is the robot's own state."""
    _check(name)
    task = TASKS[name]()
    if images:
        task.see_cameras()
    return task


def make_expert(name: str, retry: bool = False, style: OperatorStyle | str = OperatorStyle.CARRY_ON) -> Expert:
    """The task's scripted expert; ``retry``: as the simulated operator, which tries again when a plan
    ends without success (``Expert.retry``; demonstrations are recorded without); ``style``: how it
    plans at takeovers (``Expert.take_over``)."""
    _check(name)
    expert = EXPERTS[name]()
    expert.retry = retry
    expert.style = OperatorStyle(style)
    return expert

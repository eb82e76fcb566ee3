"""The ``in-process`` worker back end: the robot's ``Task`` stepped in the caller's thread when the
request is made. Deterministic and fast to start; the unit tests' fleet and small single-machine runs
use it."""

from __future__ import annotations

import traceback
from collections.abc import Callable

import numpy as np

from server.workers.base import RobotWorker, WorkerFactory, WorkerFault
from sim.env import Task
from sim.frame import RobotFrame


class InProcessWorker(RobotWorker):
    """The robot's task runs in the caller's thread: a request is answered before it returns.

    ``task``: the Task to drive (a factory makes it, so tests can pass a light stand-in).
    """

    def __init__(self, task: Task) -> None:
        super().__init__()
        self.task = task
        self._answer: RobotFrame | None = None
        self._error: str | None = None
        self._alive = True

    def _do(self, fn: Callable[[], RobotFrame]) -> None:
        if not self._alive:
            raise WorkerFault("worker was killed")
        self.busy = True
        try:
            self._answer = fn()
        except Exception:  # noqa: BLE001 - reported on poll, as a process worker would
            self._error = traceback.format_exc(limit=3)

    def request_reset(self, seed: int) -> None:
        self._do(lambda: (self.task.reset(int(seed)), RobotFrame.from_task(self.task))[1])

    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        self._do(lambda: RobotFrame.from_task(self.task, self.task.step(np.asarray(action, np.float64), hold)))

    def poll(self) -> RobotFrame | None:
        if not self._alive:
            raise WorkerFault("worker was killed")
        if self._error is not None:
            error, self._error, self.busy = self._error, None, False
            raise WorkerFault(error)
        answer, self._answer = self._answer, None
        if answer is not None:
            self.busy = False
        return answer

    def alive(self) -> bool:
        return self._alive

    def kill(self) -> None:
        self._alive, self.busy = False, False

    def close(self) -> None:
        self.kill()
        self.task.close()


def in_process_workers(make_task: Callable[[str], Task] | None = None) -> WorkerFactory:
    if make_task is None:
        from sim.registry import make_task

    def factory(robot_id: int, task: str, images: bool = False) -> InProcessWorker:
        return InProcessWorker(make_task(task, images=images) if images else make_task(task))

    return factory

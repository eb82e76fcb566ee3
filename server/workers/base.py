"""The robot worker contract: how the fleet talks to one robot, whatever runs it.

``RobotWorker`` is the seam a back end implements (spawned processes, the caller's thread, Ray actors).
Nothing above it touches processes, pipes, pids or CPU priorities. A worker takes one request at a
time (``request_reset`` / ``request_step``), answers it with a ``RobotFrame`` that ``poll`` returns
without blocking, and reports failures as ``WorkerFault``. ``wait_any`` is the free-running loop's
wait over workers of any back end; ``WorkerFactory`` is what a back end gives the fleet.

The back ends (``process``, ``pool``, ``in_process``, ``ray_actors``) implement this module and the registry
(``server.workers.registry``) names them; this module imports neither.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from enum import StrEnum

import numpy as np

from sim.frame import RobotFrame


class WorkerFault(Exception):
    """The worker died or failed a request; the message says how."""


class Priority(StrEnum):
    CONTROL = "control"  # as urgent as the control loop (a robot under teleop)
    BACKGROUND = "background"  # below the control loop (the fleet's physics)


class RobotWorker(ABC):
    """One robot. ``busy`` while a request is in flight; ``poll`` returns its answer once."""

    def __init__(self) -> None:
        self.busy = False

    @abstractmethod
    def request_reset(self, seed: int) -> None: ...

    @abstractmethod
    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        """hold: the action only holds the pose (a robot waiting for help); it does not count against the
        episode's horizon (``Task.step``)."""

    @abstractmethod
    def poll(self) -> RobotFrame | None:
        """The answer to the request in flight, if it has come (never blocks); raises WorkerFault."""

    @abstractmethod
    def alive(self) -> bool: ...

    @abstractmethod
    def kill(self) -> None:
        """Stops the robot at once (fault handling)."""

    def close(self) -> None:
        """Stops the robot cleanly (service shutdown)."""
        self.kill()

    def join(self, timeout: float) -> None:  # noqa: B027 - nothing to wait for by default
        """Waits for a closed worker to finish, up to ``timeout`` seconds."""

    def prioritize(self, priority: Priority) -> bool:
        """A hint; returns False when the back end could not honour it."""
        return True

    @classmethod
    def wait_any(
        cls, workers: Sequence[RobotWorker], timeout: float, min_ready: int = 1, urgent: Sequence[RobotWorker] = ()
    ) -> None:
        """Blocks until ``min_ready`` of ``workers``, or any of ``urgent`` (a subset), may have an answer,
        or ``timeout`` seconds."""
        if not any(w.busy for w in workers):
            time.sleep(min(timeout, 0.01))


def wait_any(
    workers: Sequence[RobotWorker], timeout: float, min_ready: int = 1, urgent: Sequence[RobotWorker] = ()
) -> None:
    """Blocks until ``min_ready`` busy workers (at least one) may have answered, or any busy one of
    ``urgent`` (a teleoperated robot: its operator's next command waits for it), or ``timeout`` seconds:
    the free-running loop's wait."""
    busy = [w for w in workers if w.busy]
    kinds = {type(w) for w in busy}
    if len(kinds) == 1:
        urgent = [w for w in urgent if w.busy]
        kinds.pop().wait_any(busy, timeout, max(1, min(min_ready, len(busy))), urgent)
    elif not busy:
        time.sleep(min(timeout, 0.01))
    # mixed back ends: do not block on one kind while another may have answered


# (robot id, task name, images) -> worker; ``images``: the task observes as a policy that sees cameras does
# (``sim.registry.make_task(name, images=True)``): its frames carry the policy cameras' images
WorkerFactory = Callable[..., RobotWorker]

"""Robot workers: how the fleet talks to its robots.

``RobotWorker`` is the seam a back end implements (a process per robot today; Ray actors later).
Nothing above it touches processes, pipes, pids or CPU priorities. A worker takes one request at a
time (``request_reset`` / ``request_step``), answers it with a ``RobotFrame`` that ``poll`` returns
without blocking, and reports failures as ``WorkerFault``.

- ``ProcessWorker``: one simulated robot per spawned process, answering on a pipe; a priority hint
  maps to the process's niceness (the control loop's own for a teleoperated robot, lower otherwise).
- ``InProcessWorker``: the robot's ``Task`` stepped in the caller's thread when the request is
  made. Deterministic and fast to start; the unit tests' fleet and small single-machine runs use it.
- ``PoolWorker`` (``server.pool_workers``): several robots per process, so one wake-up serves several
  robots' steps (a process per robot spends much of a small machine's CPU switching between them).

``WORKERS`` is the registry the settings' ``worker`` name selects from.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import time
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from enum import StrEnum
from multiprocessing.connection import Connection, wait
from typing import TYPE_CHECKING

import numpy as np

from sim.env import Task
from sim.frame import RobotFrame

if TYPE_CHECKING:
    from server.settings import Settings

log = logging.getLogger("hitl.workers")


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


# -- a process per robot ---------------------------------------------------------------------------------
def _serve(conn: Connection, task_name: str) -> None:
    """Process entry point: answers ``("reset", seed)``, ``("step", (action, hold))``, ``("close", None)``;
    exits on ``close`` or when the server's end of the pipe goes away."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from sim.registry import make_task

    task = make_task(task_name)
    try:
        while True:
            try:
                cmd, arg = conn.recv()
            except (EOFError, OSError):
                return
            try:
                if cmd == "reset":
                    task.reset(int(arg))
                    conn.send(("ok", RobotFrame.from_task(task)))
                elif cmd == "step":
                    action, hold = arg
                    conn.send(("ok", RobotFrame.from_task(task, task.step(np.asarray(action, np.float64), hold))))
                elif cmd == "close":
                    return
                else:
                    conn.send(("error", f"unknown command {cmd!r}"))
            except Exception:  # report and keep serving: the fleet decides what a fault means
                conn.send(("error", traceback.format_exc(limit=3)))
    finally:
        task.close()


class ProcessWorker(RobotWorker):
    """A spawned process per robot; ``niceness`` is the CPU priority of its background mode."""

    _ctx = mp.get_context("spawn")
    _priority_denied = False  # raising a priority needs CAP_SYS_NICE: logged once per service

    def __init__(self, task: str, name: str = "robot", niceness: int = 10) -> None:
        super().__init__()
        self.niceness = niceness
        parent, child = self._ctx.Pipe()
        self._process = self._ctx.Process(target=_serve, args=(child, task), daemon=True, name=name)
        self._process.start()
        child.close()
        self._conn = parent
        self._nice: int | None = None  # the niceness set last (None: not set since spawn)

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def _send(self, message: tuple) -> None:
        try:
            self._conn.send(message)
        except (OSError, BrokenPipeError) as exc:
            raise WorkerFault(f"worker pipe broke: {exc}") from exc
        self.busy = True

    def request_reset(self, seed: int) -> None:
        self._send(("reset", int(seed)))

    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        self._send(("step", (np.asarray(action, dtype=np.float64), bool(hold))))

    def _exited(self) -> WorkerFault | None:
        if self._process.is_alive():
            return None
        return WorkerFault(f"worker process exited (code {self._process.exitcode})")

    def poll(self) -> RobotFrame | None:
        # a busy worker that dies closes its end of the pipe, which then reads as ready: the liveness
        # check (a waitpid per call) is only needed for idle workers and broken pipes
        if not self.busy:
            if (fault := self._exited()) is not None:
                raise fault
            return None
        try:
            if not self._conn.poll():
                return None
            status, payload = self._conn.recv()
        except (EOFError, OSError) as exc:
            self._process.join(timeout=0.5)  # the exit code, once the process is gone
            raise self._exited() or WorkerFault(f"worker pipe broke: {exc}") from exc
        self.busy = False
        if status != "ok":
            raise WorkerFault(str(payload))
        return payload

    def alive(self) -> bool:
        return self._process.is_alive()

    def kill(self) -> None:
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=1.0)  # reaped: ``alive`` is False from here on
        self.busy = False

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(("close", None))

    def join(self, timeout: float) -> None:
        self._process.join(timeout=timeout)
        if self._process.is_alive():
            self._process.kill()

    def prioritize(self, priority: Priority) -> bool:
        """CONTROL runs at the control loop's niceness (0), BACKGROUND at ``niceness``. Raising a
        priority again needs CAP_SYS_NICE; without it the worker stays at ``niceness``."""
        want = 0 if priority == Priority.CONTROL else self.niceness
        if self._nice == want or self._process.pid is None:
            return True
        try:
            os.setpriority(os.PRIO_PROCESS, self._process.pid, want)
        except PermissionError:
            if not ProcessWorker._priority_denied:
                log.info("cannot raise worker priority for teleoperated robots (needs CAP_SYS_NICE)")
            ProcessWorker._priority_denied = True
            if self._nice != self.niceness:
                try:
                    os.setpriority(os.PRIO_PROCESS, self._process.pid, self.niceness)
                    self._nice = self.niceness
                except (PermissionError, ProcessLookupError):
                    pass
            return False
        except ProcessLookupError:  # exited: the next poll faults it
            return False
        self._nice = want
        return True

    @classmethod
    def wait_any(
        cls, workers: Sequence[RobotWorker], timeout: float, min_ready: int = 1, urgent: Sequence[RobotWorker] = ()
    ) -> None:
        conns = [w._conn for w in workers if isinstance(w, ProcessWorker)]
        first = {id(w._conn) for w in urgent if isinstance(w, ProcessWorker)}
        deadline = time.monotonic() + timeout
        while conns:
            ready = wait(conns, timeout=max(0.0, deadline - time.monotonic()))
            min_ready -= len(ready)
            if not ready or min_ready <= 0 or time.monotonic() >= deadline or any(id(c) in first for c in ready):
                return
            conns = [c for c in conns if c not in ready]


# -- in the caller's thread ---------------------------------------------------------------------------------
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


WorkerFactory = Callable[[int, str], RobotWorker]  # (robot id, task name) -> worker


def process_workers(niceness: int) -> WorkerFactory:
    return lambda robot_id, task: ProcessWorker(task, name=f"robot-{robot_id}", niceness=niceness)


def in_process_workers(make_task: Callable[[str], Task] | None = None) -> WorkerFactory:
    if make_task is None:
        from sim.registry import make_task
    return lambda robot_id, task: InProcessWorker(make_task(task))


def pool_workers(niceness: int, robots_per_process: int) -> WorkerFactory:
    from server.pool_workers import PoolFactory

    return PoolFactory(niceness, robots_per_process)


# the settings' ``worker`` name -> the factory built from the settings
WORKERS: dict[str, Callable[[Settings], WorkerFactory]] = {
    "process": lambda s: process_workers(s.worker_niceness),
    "pool": lambda s: pool_workers(s.worker_niceness, s.robots_per_process),
    "in-process": lambda s: in_process_workers(),
}

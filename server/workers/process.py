"""The ``process`` worker back end: one simulated robot per spawned process, answering on a pipe.

A priority hint maps to the process's niceness: the control loop's own for a teleoperated robot,
``niceness`` (lower priority) otherwise, so the batched policy step does not queue behind the physics
it feeds on a machine with fewer cores than robots.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait

import numpy as np

from server.workers.base import Priority, RobotWorker, WorkerFactory, WorkerFault
from sim.frame import RobotFrame

log = logging.getLogger("hitl.workers")


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


def process_workers(niceness: int) -> WorkerFactory:
    return lambda robot_id, task: ProcessWorker(task, name=f"robot-{robot_id}", niceness=niceness)

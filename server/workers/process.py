"""The ``process`` worker back end (the default): one simulated robot per spawned process, answering on a
pipe, so a robot's crash, niceness and kill are its own.

It shares its parts with the ``pool`` back end (``server.workers.spawn``: the spawn context, serving a
request, the pipe's readiness check, the niceness of a priority hint) and keeps its own loop: one
request, one answer.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait

import numpy as np

from server.workers.base import Priority, RobotWorker, WorkerFactory, WorkerFault
from server.workers.spawn import SPAWN, Niceness, readable, serve_request
from sim.frame import RobotFrame


def _serve(conn: Connection, task_name: str, images: bool = False) -> None:
    """Process entry point: answers ``("reset", seed)``, ``("step", (action, hold))``, ``("close", None)``;
    exits on ``close`` or when the server's end of the pipe goes away."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from sim.registry import make_task

    task = make_task(task_name, images=images)
    try:
        while True:
            try:
                cmd, arg = conn.recv()
            except (EOFError, OSError):
                return
            if cmd in ("reset", "step"):
                conn.send(serve_request(task, cmd, arg))
            elif cmd == "close":
                return
            else:
                conn.send(("error", f"unknown command {cmd!r}"))
    finally:
        task.close()


class ProcessWorker(RobotWorker):
    """A spawned process per robot; ``niceness`` is the CPU priority of its background mode."""

    def __init__(self, task: str, name: str = "robot", niceness: int = 10, images: bool = False) -> None:
        super().__init__()
        self.niceness = Niceness(niceness)
        parent, child = SPAWN.Pipe()
        self._process = SPAWN.Process(target=_serve, args=(child, task, images), daemon=True, name=name)
        self._process.start()
        child.close()
        self._conn = parent
        self._readable = readable(parent)

    @property
    def pid(self) -> int | None:
        return self._process.pid

    @property
    def name(self) -> str:
        """Its process's name (``robot-<id>`` in the fleet)."""
        return self._process.name

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
            if not self._readable.poll(0):
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
        """CONTROL runs at the control loop's niceness (0), BACKGROUND at ``niceness`` (``Niceness``)."""
        return self.niceness.apply(self._process.pid, priority == Priority.CONTROL)

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
    def factory(robot_id: int, task: str, images: bool = False) -> ProcessWorker:
        return ProcessWorker(task, name=f"robot-{robot_id}", niceness=niceness, images=images)

    return factory

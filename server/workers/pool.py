"""The ``pool`` worker back end: several simulated robots per process.

With a process per robot, every control step of every robot is a context switch into another
process: on a 2-core machine with 16 robots the workers spent 5.8 ms of CPU per env step against 3.9
for one robot's worker alone (``hitl bench fleet``, ``docs/benchmarks/serving.md``). A host process here owns
up to ``robots_per_process`` robots' tasks and answers their requests one at a time, a teleoperated
robot's first, so one wake-up serves several robots and the fleet runs a few processes instead of one
per robot (4.45 ms per env step at 16 robots, and a quarter of the memory).

Each robot still has its own ``PoolWorker`` (the ``RobotWorker`` contract: one request in flight,
``poll`` never blocks, failures are ``WorkerFault``). A robot's error faults that robot only; a host
process that dies faults every robot it held, and each is restarted on a live host (or a new one).
Priorities apply per host: it runs at the control loop's niceness while any of its robots is under
teleop (when the service may raise it), at the workers' niceness otherwise.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait

import numpy as np

from server.workers.base import Priority, RobotWorker, WorkerFault
from sim.frame import RobotFrame


def _host(conn: Connection) -> None:
    """Process entry point: ``(cmd, rid, seq, arg)`` with cmd ``open`` (arg: the task's name), ``reset``
    (the seed), ``step`` ((action, hold)), ``urgent`` (whether the robot is under teleop), ``drop`` or
    ``close``; answers ``(rid, seq, status, payload)`` to resets and steps (``seq`` tells a robot's answer
    from a dropped predecessor's). It serves one request at a time and reads the pipe between two: the next
    is an urgent robot's if one waits, so an operator's step never queues behind the other robots' physics."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from sim.registry import make_task

    tasks, urgent, failed = {}, set(), {}

    def answer(cmd: str, rid: int, seq: int, arg) -> None:
        if rid in failed:  # its task could not be built
            conn.send((rid, seq, "error", failed[rid]))
            return
        try:
            if cmd == "reset":
                tasks[rid].reset(int(arg))
                conn.send((rid, seq, "ok", RobotFrame.from_task(tasks[rid])))
            else:
                action, hold = arg
                task = tasks[rid]
                frame = RobotFrame.from_task(task, task.step(np.asarray(action, np.float64), hold))
                conn.send((rid, seq, "ok", frame))
        except Exception:  # one robot's error: reported to that robot, the others carry on
            conn.send((rid, seq, "error", traceback.format_exc(limit=3)))

    pending: list[tuple] = []  # resets and steps not answered yet, in arrival order
    try:
        while True:
            try:  # everything that has arrived (block only when there is nothing left to do)
                waiting = [] if pending else [conn.recv()]
                while conn.poll():
                    waiting.append(conn.recv())
            except (EOFError, OSError):
                return
            for cmd, rid, seq, arg in waiting:
                if cmd in ("reset", "step"):
                    pending.append((cmd, rid, seq, arg))
                elif cmd == "open":
                    failed.pop(rid, None)
                    try:
                        tasks[rid] = make_task(arg)
                    except Exception:  # reported on the robot's requests
                        failed[rid] = traceback.format_exc(limit=3)
                elif cmd == "urgent":
                    (urgent.add if arg else urgent.discard)(rid)
                elif cmd == "drop":
                    urgent.discard(rid)
                    failed.pop(rid, None)
                    pending = [r for r in pending if r[1] != rid]
                    task = tasks.pop(rid, None)
                    if task is not None:
                        task.close()
                elif cmd == "close":
                    return
                else:
                    conn.send((rid, seq, "error", f"unknown command {cmd!r}"))
            if pending:  # one request, then look at the pipe again: an urgent one never waits for a queue
                first = next((i for i, r in enumerate(pending) if r[1] in urgent), 0)
                answer(*pending.pop(first))
    finally:
        for task in tasks.values():
            with contextlib.suppress(Exception):
                task.close()


class _Host:
    """One host process and the answers it has sent that no robot has polled yet."""

    _ctx = mp.get_context("spawn")

    def __init__(self, name: str, niceness: int) -> None:
        parent, child = self._ctx.Pipe()
        self.process = self._ctx.Process(target=_host, args=(child,), daemon=True, name=name)
        self.process.start()
        child.close()
        self.conn = parent
        self.niceness = niceness
        self.robots: set[int] = set()
        self.control: set[int] = set()  # robots that asked for the control loop's priority
        self.answers: dict[tuple[int, int], tuple[str, object]] = {}  # (robot, seq) -> (status, payload)
        self.seq = 0
        self.broken: str | None = None
        self._nice: int | None = None
        self.renice()

    def alive(self) -> bool:
        return self.broken is None and self.process.is_alive()

    def send(self, message: tuple) -> None:
        if self.broken is not None:
            raise WorkerFault(self.broken)
        try:
            self.conn.send(message)
        except (OSError, BrokenPipeError) as exc:
            self._break(f"worker pipe broke: {exc}")
            raise WorkerFault(self.broken) from exc

    def drain(self) -> None:
        """Moves every answer waiting in the pipe into ``answers`` (never blocks)."""
        if self.broken is not None:
            return
        try:
            while self.conn.poll():
                rid, seq, status, payload = self.conn.recv()
                self.answers[(rid, seq)] = (status, payload)
        except (EOFError, OSError) as exc:
            self.process.join(timeout=0.5)
            code = self.process.exitcode
            self._break(f"worker process exited (code {code})" if code is not None else f"worker pipe broke: {exc}")

    def _break(self, why: str) -> None:
        self.broken = why
        with contextlib.suppress(Exception):
            self.process.kill()

    def renice(self) -> bool:
        want = 0 if self.control else self.niceness
        if self._nice == want or self.process.pid is None:
            return True
        try:
            os.setpriority(os.PRIO_PROCESS, self.process.pid, want)
        except PermissionError:
            if self._nice is None:
                with contextlib.suppress(PermissionError, ProcessLookupError):
                    os.setpriority(os.PRIO_PROCESS, self.process.pid, self.niceness)
                    self._nice = self.niceness
            return False
        except ProcessLookupError:
            return False
        self._nice = want
        return True

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(("close", None, 0, None))

    def join(self, timeout: float) -> None:
        self.process.join(timeout=timeout)
        if self.process.is_alive():
            self.process.kill()


class PoolWorker(RobotWorker):
    """One robot on a shared host process."""

    def __init__(self, host: _Host, robot_id: int, task: str) -> None:
        super().__init__()
        self.host, self.robot_id = host, robot_id
        self._killed = False
        self._seq = 0  # the request in flight
        host.robots.add(robot_id)
        host.send(("open", robot_id, 0, task))

    @property
    def pid(self) -> int | None:
        """The host process this robot's physics runs in (shared with the host's other robots)."""
        return self.host.process.pid

    @property
    def _key(self) -> tuple[int, int]:
        return (self.robot_id, self._seq)

    def _request(self, cmd: str, arg) -> None:
        if self._killed:
            raise WorkerFault("worker was killed")
        for stale in [k for k in self.host.answers if k[0] == self.robot_id]:  # a dropped predecessor's
            del self.host.answers[stale]
        self.host.seq += 1
        self._seq = self.host.seq
        self.host.send((cmd, self.robot_id, self._seq, arg))
        self.busy = True

    def request_reset(self, seed: int) -> None:
        self._request("reset", int(seed))

    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        self._request("step", (np.asarray(action, dtype=np.float64), bool(hold)))

    def poll(self) -> RobotFrame | None:
        if self._killed:
            raise WorkerFault("worker was killed")
        self.host.drain()
        answer = self.host.answers.pop(self._key, None) if self.busy else None
        if answer is None:
            if not self.host.alive():
                raise WorkerFault(self.host.broken or f"worker process exited (code {self.host.process.exitcode})")
            return None
        self.busy = False
        status, payload = answer
        if status != "ok":
            raise WorkerFault(str(payload))
        return payload

    def alive(self) -> bool:
        return not self._killed and self.host.alive()

    def kill(self) -> None:
        """Drops this robot from its host (the host and its other robots carry on)."""
        if not self._killed:
            self._killed = True
            self.host.robots.discard(self.robot_id)
            self.host.control.discard(self.robot_id)
            self.host.answers.pop(self._key, None)
            with contextlib.suppress(WorkerFault):
                self.host.send(("drop", self.robot_id, 0, None))
            self.host.renice()
        self.busy = False

    def close(self) -> None:
        self.kill()
        if not self.host.robots:
            self.host.close()

    def join(self, timeout: float) -> None:
        if not self.host.robots:
            self.host.join(timeout)

    def prioritize(self, priority: Priority) -> bool:
        """CONTROL: the host serves this robot's requests before its other robots', and runs at the
        control loop's niceness while it has such a robot (when the service may raise it)."""
        urgent = priority == Priority.CONTROL
        if urgent != (self.robot_id in self.host.control) and not self._killed:
            (self.host.control.add if urgent else self.host.control.discard)(self.robot_id)
            with contextlib.suppress(WorkerFault):  # a broken host faults the robot at its next poll
                self.host.send(("urgent", self.robot_id, 0, urgent))
        return self.host.renice()

    @classmethod
    def wait_any(
        cls, workers: Sequence[RobotWorker], timeout: float, min_ready: int = 1, urgent: Sequence[RobotWorker] = ()
    ) -> None:
        pool = [w for w in workers if isinstance(w, PoolWorker)]
        first = [w for w in urgent if isinstance(w, PoolWorker)]
        hosts = list({id(w.host): w.host for w in pool}.values())
        deadline = time.monotonic() + timeout
        while True:
            for host in hosts:
                host.drain()
            ready = sum(1 for w in pool if w._key in w.host.answers or not w.host.alive())
            left = deadline - time.monotonic()
            if ready >= min_ready or left <= 0 or any(w._key in w.host.answers for w in first):
                return
            if not wait([h.conn for h in hosts if h.alive()] or [], timeout=left):
                return


class PoolFactory:
    """Places each new robot on the live host with the fewest robots, below ``robots_per_process``;
    starts a host when none has room. Hosts whose robots all left are closed."""

    def __init__(self, niceness: int, robots_per_process: int) -> None:
        if robots_per_process < 1:
            raise ValueError(f"robots_per_process must be >= 1, got {robots_per_process}")
        self.niceness, self.per_process = niceness, robots_per_process
        self.hosts: list[_Host] = []
        self._started = 0  # hosts started so far (their process names: robots-0, robots-1, ...)

    def __call__(self, robot_id: int, task: str) -> PoolWorker:
        for host in [h for h in self.hosts if not h.robots or not h.alive()]:
            if host.alive():
                host.close()
            self.hosts.remove(host)
        room = [h for h in self.hosts if len(h.robots) < self.per_process]
        host = min(room, key=lambda h: len(h.robots)) if room else None
        if host is None:
            host = _Host(f"robots-{self._started}", self.niceness)
            self._started += 1
            self.hosts.append(host)
        return PoolWorker(host, robot_id, task)

"""The ``pool`` worker back end: several simulated robots per spawned process.

With a process per robot, every control step of every robot is a context switch into another
process, which costs CPU per env step (``hitl bench fleet``, ``docs/benchmarks/serving.md``). A host process here owns
up to ``robots_per_process`` robots' tasks and answers their requests one at a time, a teleoperated
robot's first, so one wake-up serves several robots and the fleet runs a few processes instead of one
per robot.

Each robot still has its own ``PoolWorker`` (the ``RobotWorker`` contract: one request in flight,
``poll`` never blocks, failures are ``WorkerFault``). A robot's error faults that robot only; a host
process that dies faults every robot it held, and each is restarted on a live host (or a new one).
Priorities apply per host: it runs at the control loop's niceness while any of its robots is under
teleop (when the service may raise it), at the workers' niceness otherwise.

It shares its parts with the ``process`` back end (``server.workers.spawn``); killing the robot of a
one-robot host (``robots_per_process = 1``) kills the host.
"""

from __future__ import annotations

import contextlib
import os
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait

import numpy as np

from server.workers.base import Priority, RobotWorker, WorkerFactory, WorkerFault
from server.workers.spawn import SPAWN, Niceness, readable, serve_request
from sim.frame import RobotFrame


def _host(conn: Connection) -> None:
    """Process entry point: ``(cmd, rid, seq, arg)`` with cmd ``open`` (arg: the task's name and whether it
    renders the policy's cameras), ``reset``
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
        else:  # one robot's error is reported to that robot, the others carry on
            conn.send((rid, seq, *serve_request(tasks[rid], cmd, arg)))

    pending: list[tuple] = []  # resets and steps not answered yet, in arrival order
    arrived = readable(conn)
    try:
        while True:
            try:  # everything that has arrived (block only when there is nothing left to do)
                waiting = [] if pending else [conn.recv()]
                while arrived.poll(0):
                    waiting.append(conn.recv())
            except (EOFError, OSError):
                return
            for cmd, rid, seq, arg in waiting:
                if cmd in ("reset", "step"):
                    pending.append((cmd, rid, seq, arg))
                elif cmd == "open":
                    failed.pop(rid, None)
                    try:
                        tasks[rid] = make_task(arg[0], images=arg[1])
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
    """One host process and the answers it has sent that no robot has polled yet. A host of ``capacity``
    1 is its robot's own process."""

    def __init__(self, name: str, niceness: int, capacity: int) -> None:
        parent, child = SPAWN.Pipe()
        self.process = SPAWN.Process(target=_host, args=(child,), daemon=True, name=name)
        self.process.start()
        child.close()
        self.conn = parent
        self._arrived = readable(parent)
        self.niceness, self.capacity = Niceness(niceness), capacity
        self.robots: set[int] = set()
        self.control: set[int] = set()  # robots that asked for the control loop's priority
        self.answers: dict[tuple[int, int], tuple[str, object]] = {}  # (robot, seq) -> (status, payload)
        self.seq = 0
        self.broken: str | None = None
        self.renice()

    def alive(self) -> bool:
        return self.broken is None and self.process.is_alive()

    def fault(self) -> WorkerFault:
        return WorkerFault(self.broken or f"worker process exited (code {self.process.exitcode})")

    def send(self, message: tuple) -> None:
        if self.broken is not None:
            raise WorkerFault(self.broken)
        try:
            self.conn.send(message)
        except (OSError, BrokenPipeError) as exc:
            self._break(f"worker pipe broke: {exc}")
            raise WorkerFault(self.broken) from exc

    def drain(self, until: tuple[int, int] | None = None, ready: bool = False) -> tuple[str, object] | None:
        """Moves the answers waiting in the pipe into ``answers`` (never blocks), up to ``until``'s, which
        it returns instead; ``ready``: the pipe is known to be readable, one answer is read without polling
        it. A host that died closed its end of the pipe, which reads as ready: its exit is found here,
        without a liveness check (a ``waitpid``) per busy robot per tick."""
        if self.broken is not None:
            return None
        try:
            while ready or self._arrived.poll(0):
                rid, seq, status, payload = self.conn.recv()
                if (rid, seq) == until:
                    return status, payload
                self.answers[(rid, seq)] = (status, payload)
                if ready:
                    return None
        except (EOFError, OSError) as exc:
            self.process.join(timeout=0.5)
            code = self.process.exitcode
            self._break(f"worker process exited (code {code})" if code is not None else f"worker pipe broke: {exc}")
        return None

    def _break(self, why: str) -> None:
        self.broken = why
        with contextlib.suppress(Exception):
            self.process.kill()

    def renice(self) -> bool:
        """The control loop's niceness while a robot here is under teleop, the workers' otherwise."""
        return self.niceness.apply(self.process.pid, bool(self.control))

    def kill(self) -> None:
        self._break(self.broken or "worker was killed")
        self.process.join(timeout=1.0)  # reaped: not alive from here on

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(("close", None, 0, None))

    def join(self, timeout: float) -> None:
        self.process.join(timeout=timeout)
        if self.process.is_alive():
            self.process.kill()


class PoolWorker(RobotWorker):
    """One robot on a host process, shared with the host's other robots (up to ``robots_per_process``)."""

    def __init__(self, host: _Host, robot_id: int, task: str, images: bool = False) -> None:
        super().__init__()
        self.host, self.robot_id = host, robot_id
        self._killed = False
        self._key = (robot_id, 0)  # the request in flight: (robot, seq)
        host.robots.add(robot_id)
        host.send(("open", robot_id, 0, (task, images)))

    @property
    def pid(self) -> int | None:
        """The host process this robot's physics runs in (shared with the host's other robots)."""
        return self.host.process.pid

    def _request(self, cmd: str, arg) -> None:
        if self._killed:
            raise WorkerFault("worker was killed")
        host = self.host
        if host.answers:  # a dropped predecessor's
            for stale in [k for k in host.answers if k[0] == self.robot_id]:
                del host.answers[stale]
        host.seq += 1
        self._key = (self.robot_id, host.seq)
        host.send((cmd, self.robot_id, host.seq, arg))
        self.busy = True

    def request_reset(self, seed: int) -> None:
        self._request("reset", int(seed))

    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        self._request("step", (np.asarray(action, dtype=np.float64), bool(hold)))

    def poll(self) -> RobotFrame | None:
        if self._killed:
            raise WorkerFault("worker was killed")
        host = self.host
        if not self.busy:  # nothing to read: only whether its process still lives
            if not host.alive():
                raise host.fault()
            return None
        answer = host.answers.pop(self._key, None) or host.drain(self._key)
        if answer is None:
            if host.broken is not None:
                raise host.fault()
            return None
        self.busy = False
        status, payload = answer
        if status != "ok":
            raise WorkerFault(str(payload))
        return payload

    def alive(self) -> bool:
        return not self._killed and self.host.alive()

    def _leave(self, kill: bool) -> None:
        if not self._killed:
            self._killed = True
            self.host.robots.discard(self.robot_id)
            self.host.control.discard(self.robot_id)
            self.host.answers.pop(self._key, None)
            if kill and self.host.capacity == 1:  # its own process: a step that never returns stops too
                self.host.kill()
            else:
                with contextlib.suppress(WorkerFault):
                    self.host.send(("drop", self.robot_id, 0, None))
                self.host.renice()
        self.busy = False

    def kill(self) -> None:
        """Drops this robot from its host (the host and its other robots carry on); a host of one robot
        is killed with it."""
        self._leave(kill=True)

    def close(self) -> None:
        self._leave(kill=False)
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
        deadline = time.monotonic() + timeout
        while True:  # a host that died reads as ready (its drain marks it broken)
            owing = [w for w in pool if w.host.broken is None and w._key not in w.host.answers]
            ready = len(pool) - len(owing)
            if ready >= min_ready or any(w._key in w.host.answers for w in first):
                return
            hosts = {id(w.host.conn): w.host for w in owing}
            conns = [h.conn for h in hosts.values()]
            urgent_conns = {id(w.host.conn) for w in first}
            while True:
                left = deadline - time.monotonic()
                got = wait(conns, timeout=left) if left > 0 else []
                if not got:
                    return
                shared = [hosts[id(c)] for c in got if hosts[id(c)].capacity > 1]
                if shared:  # several robots' answers may be waiting: read them, then count again
                    for host in shared:
                        host.drain(ready=True)
                    break
                # one-robot hosts: each that answered (or died) is one robot ready, which its poll reads
                ready += len(got)
                if ready >= min_ready or any(id(c) in urgent_conns for c in got):
                    return
                conns = [c for c in conns if c not in got]


class PoolFactory:
    """Places each new robot on the live host with the fewest robots, below ``robots_per_process``;
    starts a host when none has room. Hosts whose robots all left are closed. ``name``: the host
    processes' names, from ``{host}`` (hosts started so far) and ``{robot}`` (the first robot's id)."""

    def __init__(self, niceness: int, robots_per_process: int, name: str = "robots-{host}") -> None:
        if robots_per_process < 1:
            raise ValueError(f"robots_per_process must be >= 1, got {robots_per_process}")
        self.niceness, self.per_process, self.name = niceness, robots_per_process, name
        self.hosts: list[_Host] = []
        self._started = 0  # hosts started so far (their process names: robots-0, robots-1, ...)

    def __call__(self, robot_id: int, task: str, images: bool = False) -> PoolWorker:
        for host in [h for h in self.hosts if not h.robots or not h.alive()]:
            if host.alive():
                host.close()
            self.hosts.remove(host)
        room = [h for h in self.hosts if len(h.robots) < self.per_process]
        host = min(room, key=lambda h: len(h.robots)) if room else None
        if host is None:
            host = _Host(self.name.format(host=self._started, robot=robot_id), self.niceness, self.per_process)
            self._started += 1
            self.hosts.append(host)
        return PoolWorker(host, robot_id, task, images)


def pool_workers(niceness: int, robots_per_process: int) -> WorkerFactory:
    return PoolFactory(niceness, robots_per_process)

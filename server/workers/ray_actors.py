"""The ``ray`` worker back end: robots as Ray actors, several robots per actor, as the pool hosts them.

A ``RobotHost`` actor owns up to ``robots_per_process`` robots' tasks and answers one request at a
time; each robot has its own ``RayWorker`` (the ``RobotWorker`` contract: one request in flight as an
``ObjectRef``, ``poll`` never blocks, failures are ``WorkerFault``). On a cluster the actors land on
any node with a free CPU share (``ray_cpus_per_actor``), so physics leaves the service's machine.

Failures. A robot's error (a bad action, a task that cannot be built) faults that robot only. An
actor that dies faults every robot with a request in flight on it (``ray.exceptions.RayActorError``),
and the others at their next request. Ray restarts the actor (``max_restarts=-1``), on any live node;
the fleet restarts each faulted robot with its usual backoff, and the robot is opened again on its
host once the host is back. A host whose robots all left is killed for good.

Priorities: Ray runs an actor's calls in the order they were sent, so a teleoperated robot's step
cannot go ahead of its host's other robots (at most ``robots_per_process - 1`` steps);
``prioritize(CONTROL)`` says so by returning False.

Ray is imported only when the back end is used (``server.ray_cluster``).
"""

from __future__ import annotations

import contextlib
import copy
import os
import time
import traceback
import uuid
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from server.ray_cluster import connect
from server.workers.base import Priority, RobotWorker, WorkerFault
from sim.frame import RobotFrame


class RobotHost:
    """The actor: several robots' tasks in one process. Errors raised here reach the caller as Ray
    task errors, which ``RayWorker`` reports as the robot's ``WorkerFault``."""

    def __init__(self) -> None:
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        self.tasks: dict = {}

    def open(self, rid: int, task: str, images: bool = False) -> None:
        from sim.registry import make_task

        self.drop(rid)
        self.tasks[rid] = make_task(task, images=images)

    def reset(self, rid: int, seed: int) -> RobotFrame:
        task = self._task(rid)
        task.reset(int(seed))
        return RobotFrame.from_task(task)

    def step(self, rid: int, action: np.ndarray, hold: bool) -> RobotFrame:
        task = self._task(rid)
        return RobotFrame.from_task(task, task.step(np.asarray(action, np.float64), bool(hold)))

    def drop(self, rid: int) -> None:
        task = self.tasks.pop(rid, None)
        if task is not None:
            with contextlib.suppress(Exception):
                task.close()

    def pid(self) -> int:
        return os.getpid()

    def _task(self, rid: int):
        if rid not in self.tasks:  # the actor restarted since the robot was opened: its task is gone
            raise RuntimeError(f"robot {rid} is not open on this actor (the actor restarted)")
        return self.tasks[rid]


@dataclass
class RayOverhead:
    """Time the control loop's thread spends in Ray's API for the robots (sending requests, asking
    whether answers came and fetching them), not waiting: what Ray costs the loop per tick."""

    calls: int = 0
    seconds: float = 0.0

    def timed(self, fn, *args, **kwargs):
        start = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start
            self.calls += 1


class _Host:
    """A ``RobotHost`` actor handle and the robots placed on it."""

    def __init__(self, ray, actor_class, name: str, overhead: RayOverhead) -> None:
        self.ray, self.name, self.overhead = ray, name, overhead
        self.handle = actor_class.options(name=name).remote()
        self.robots: set[int] = set()
        self.gone = False  # killed for good (its robots all left)
        self._pid: int | None = None

    @property
    def pid(self) -> int | None:
        """The actor's process id (on its node; asked once per actor process), None when it cannot answer."""
        if self._pid is None and not self.gone:
            with contextlib.suppress(Exception):
                self._pid = int(self.ray.get(self.handle.pid.remote(), timeout=30))
        return self._pid

    def kill(self) -> None:
        if not self.gone:
            self.gone = True
            with contextlib.suppress(Exception):
                self.ray.kill(self.handle, no_restart=True)


class RayWorker(RobotWorker):
    """One robot on a ``RobotHost`` actor."""

    def __init__(self, host: _Host, robot_id: int, task: str, images: bool = False) -> None:
        super().__init__()
        self.host, self.robot_id, self.ray = host, robot_id, host.ray
        self._killed = False
        self._ref = None  # the request in flight
        host.robots.add(robot_id)
        self._opened = host.handle.open.remote(robot_id, task, images)  # its errors arrive with the first request

    @property
    def pid(self) -> int | None:
        """The process this robot's physics runs in (its actor's, shared with the actor's other robots)."""
        return self.host.pid

    def _call(self, method: str, *args) -> None:
        if self._killed:
            raise WorkerFault("worker was killed")
        self._ref = self.host.overhead.timed(getattr(self.host.handle, method).remote, self.robot_id, *args)
        self.busy = True

    def request_reset(self, seed: int) -> None:
        self._call("reset", int(seed))

    def request_step(self, action: np.ndarray, hold: bool = False) -> None:
        self._call("step", np.asarray(action, dtype=np.float64), bool(hold))

    def _get(self, ref):
        """The answer of ``ref`` (ready), or WorkerFault saying how the request or the actor failed."""
        errors = self.ray.exceptions
        try:
            return self.ray.get(ref, timeout=0)
        except errors.RayTaskError as exc:  # the robot's own error: its traceback, as the other back ends
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            raise WorkerFault("".join(traceback.format_exception_only(type(cause), cause)).strip()) from None
        except (errors.RayActorError, errors.ActorUnavailableError) as exc:
            raise WorkerFault(f"robot actor {self.host.name} died: {type(exc).__name__}") from None
        except errors.RayError as exc:
            raise WorkerFault(f"ray: {type(exc).__name__}: {exc}") from None

    def poll(self) -> RobotFrame | None:
        if self._killed:
            raise WorkerFault("worker was killed")
        if not self.busy:
            return None
        return self.host.overhead.timed(self._answer)

    def _answer(self) -> RobotFrame | None:
        ready, _ = self.ray.wait([self._ref], timeout=0, fetch_local=True)
        if not ready:
            return None
        self.busy = False
        ref, self._ref = self._ref, None
        if self._opened is not None:  # the task could not be built: that error is this request's answer
            opened, self._opened = self._opened, None
            self._get(opened)
        # Ray hands numpy arrays over read-only (zero-copy from its object store); the fleet's frames are
        # the robot's own, as the other back ends' unpickled ones are
        return copy.deepcopy(self._get(ref))

    def alive(self) -> bool:
        return not self._killed and not self.host.gone

    def kill(self) -> None:
        """Drops this robot from its host (the host and its other robots carry on)."""
        if not self._killed:
            self._killed = True
            self.host.robots.discard(self.robot_id)
            with contextlib.suppress(Exception):
                self.host.handle.drop.remote(self.robot_id)
        self.busy, self._ref = False, None

    def close(self) -> None:
        self.kill()
        if not self.host.robots:
            self.host.kill()

    def prioritize(self, priority: Priority) -> bool:
        return priority == Priority.BACKGROUND  # an actor serves its calls in order (see the module)

    @classmethod
    def wait_any(
        cls, workers: Sequence[RobotWorker], timeout: float, min_ready: int = 1, urgent: Sequence[RobotWorker] = ()
    ) -> None:
        busy = [w for w in workers if isinstance(w, RayWorker) and w._ref is not None]
        if not busy:
            time.sleep(min(timeout, 0.01))
            return
        ray = busy[0].ray
        refs = [w._ref for w in busy]
        first = {w._ref for w in urgent if isinstance(w, RayWorker) and w._ref is not None}
        if not first:
            ray.wait(refs, num_returns=min(min_ready, len(refs)), timeout=timeout, fetch_local=False)
            return
        deadline = time.monotonic() + timeout
        while True:  # in short slices, so that an urgent robot's answer ends the wait at once
            ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0, fetch_local=False)
            left = deadline - time.monotonic()
            if len(ready) >= min_ready or first.intersection(ready) or left <= 0:
                return
            ray.wait(list(first), num_returns=1, timeout=min(left, 0.002), fetch_local=False)


class RayFactory:
    """Places each new robot on the host with the fewest robots, below ``robots_per_actor``; starts an
    actor when none has room. Hosts whose robots all left are killed."""

    def __init__(self, settings, robots_per_actor: int, cpus_per_actor: float) -> None:
        if robots_per_actor < 1:
            raise ValueError(f"robots_per_actor must be >= 1, got {robots_per_actor}")
        self.settings, self.per_actor, self.cpus = settings, robots_per_actor, cpus_per_actor
        self.hosts: list[_Host] = []
        self._started = 0
        self.overhead = RayOverhead()  # shared by this factory's robots (``hitl bench fleet`` reports it)
        self._id = uuid.uuid4().hex[:8]  # this factory's actors' names: robots-<id>-0, robots-<id>-1, ...
        self._ray = None
        self._actor = None

    def _actor_class(self):
        if self._actor is None:
            self._ray = connect(self.settings)
            self._actor = self._ray.remote(num_cpus=self.cpus, max_restarts=-1, max_task_retries=0)(RobotHost)
        return self._ray, self._actor

    def __call__(self, robot_id: int, task: str, images: bool = False) -> RayWorker:
        ray, actor = self._actor_class()
        for host in [h for h in self.hosts if not h.robots or h.gone]:
            host.kill()
            self.hosts.remove(host)
        room = [h for h in self.hosts if len(h.robots) < self.per_actor]
        host = min(room, key=lambda h: len(h.robots)) if room else None
        if host is None:
            host = _Host(ray, actor, f"robots-{self._id}-{self._started}", self.overhead)
            self._started += 1
            self.hosts.append(host)
        return RayWorker(host, robot_id, task, images)

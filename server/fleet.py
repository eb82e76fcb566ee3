"""The fleet runtime: the control loop over the robot workers, and the service methods the API calls.

``Fleet`` is the public entry point: it holds the fleet's state (robots, the assistance queue, the
recorder, the lock, the counters), builds the robots from the settings, and starts and stops the two
threads (the control loop and the policy registry's watcher). Its jobs live in their own modules:

- ``server.fleet_loop``: the control tick, its loop thread, and the workers' and episodes' lives
  (a mixin: every tick reads and changes the whole fleet's state);
- ``server.fleet_operators``: the service methods operators, admins and consoles call (a mixin, on
  the same state, ending takeovers and episodes through the control loop's transitions);
- ``server.policy_swap``: policy hot swap, which version each lineage serves (a collaborator that
  owns the loaded policy slots and only reads the robots, under the fleet lock);
- ``server.fleet_metrics``: the metrics report, from the recorder's totals and the fleet's counters.

Modes: ``autonomous -> waiting -> teleop -> autonomous`` (the controller's), plus ``paused`` (not
stepped: the scene and the episode clock are frozen), ``done`` (then the next episode starts) and
``faulted`` (the worker died; it is restarted with backoff). One re-entrant lock (``Fleet.lock``)
guards the robots: a tick holds it, and so does each service method that changes a robot, except
heartbeats and teleop commands, which never wait for a tick in progress.
"""

from __future__ import annotations

import threading
from collections import deque
from pathlib import Path

import torch
from sqlalchemy.orm import sessionmaker

from server import registry
from server.assistance import AssistanceQueue
from server.commands import CommandMailbox
from server.fleet_loop import ControlLoop
from server.fleet_metrics import fleet_metrics
from server.fleet_operators import OperatorMethods
from server.policy_swap import PolicySwap
from server.recording import Recorder
from server.robot import Robot
from server.settings import Settings
from server.slots import PolicySlot
from server.workers import WORKERS, WorkerFactory
from sim.registry import make_task


class Fleet(ControlLoop, OperatorMethods):
    """workers: how robots are started (default: the settings' ``worker`` back end)."""

    def __init__(self, settings: Settings, sessions: sessionmaker, workers: WorkerFactory | None = None) -> None:
        self.settings = settings
        self.sessions = sessions
        self.queue = AssistanceQueue(settings.lease_seconds)
        self.recorder = Recorder(
            sessions,
            settings.data_dir,
            settings.record_episodes,
            settings.segment_flush_seconds,
            settings.segment_fsync,
        )
        self.robots: dict[int, Robot] = {}
        self.lock = threading.RLock()
        self.policies = PolicySwap(settings, sessions, self.lock, self.robots)  # slots, and the lineages' versions
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._watcher: threading.Thread | None = None
        self.ticks = 0
        self.env_steps = 0  # actions sent to workers, all robots, since start
        self.tick_periods: deque = deque(maxlen=2000)
        self.loop_cpu_seconds = 0.0  # CPU time of the control loop's ticks
        self.inference_holds = 0  # robot-steps held since an inference back end last failed to answer
        self.operator_busy: dict[str, float] = {}  # seconds in control, per operator
        self.operator_since: dict[str, float] = {}  # first claim, per operator
        # how robots are started (the back end); public for the benchmarks, which read its overheads
        self.worker_factory = workers if workers is not None else WORKERS[settings.worker](settings)
        self._build()

    @property
    def slots(self) -> dict[int, PolicySlot]:
        """The loaded policy versions, by version id (``PolicySwap.slots``)."""
        return self.policies.slots

    @property
    def assigned(self) -> dict[str, PolicySlot]:
        """Lineage -> the slot its robots move to at their next episode (``PolicySwap.assigned``)."""
        return self.policies.assigned

    # -- set-up -------------------------------------------------------------------------------------------
    def _build(self) -> None:
        rid = 0
        for group in self.settings.robots:
            slot = self.policies.serve(group.policy_dir, group.task)
            limits = make_task(group.task).action_space.limits
            for _ in range(group.count):
                self.robots[rid] = Robot(rid, group.task, slot, self.settings.seed + 1000 * rid, CommandMailbox(limits))
                rid += 1

    def start(self) -> None:
        # the physics workers keep the cores busy: intra-op threads in the server only contend with them
        torch.set_num_threads(self.settings.torch_threads)
        for robot in self.robots.values():
            self._spawn(robot)
        self._thread = threading.Thread(target=self._loop, name="fleet-control", daemon=True)
        self._thread.start()
        self._watcher = threading.Thread(target=self._watch_registry, name="fleet-registry", daemon=True)
        self._watcher.start()

    def _watch_registry(self) -> None:
        self.policies.watch(self._stop)

    def stop(self) -> None:
        """Finishes the current tick, closes open segments and episodes, stops the workers."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        if self._watcher is not None:
            self._watcher.join(timeout=30)
        with self.lock:
            for robot in self.robots.values():
                self._interrupt(robot, "stopped", "service-stopped")
                if robot.worker is not None:
                    robot.worker.close()
            for robot in self.robots.values():
                if robot.worker is not None:
                    robot.worker.join(timeout=5)
            served = {id(s): s for s in [*(r.slot for r in self.robots.values()), *self.slots.values()]}
            for slot in served.values():
                slot.controller.inference.close()  # an inference actor, if the slot has one

    @property
    def data_dir(self) -> Path:
        return self.settings.data_dir

    @property
    def remote(self) -> bool:
        """The fleet runs in this process: its calls never cross to another."""
        return False

    # -- policy versions (``server.policy_swap``) ----------------------------------------------------------
    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int:
        """Adds a policy folder as a ``candidate`` version (idempotent by path); returns its id."""
        return self.policies.register_policy(path, task, parent)

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]:
        """The registry's lineages with their active version and last fine-tuning job, at most
        ``max_age`` seconds old."""
        return self.policies.lineages(max_age)

    def served_lineages(self) -> set[str]:
        return self.policies.served_lineages()

    def sync_policies(self) -> list[int]:
        """Assigns each served lineage the registry's active version (loaded first); returns the versions
        newly assigned (``PolicySwap.sync_policies``)."""
        return self.policies.sync_policies()

    def activate_policy(self, version: int, reason: str | None = None) -> None:
        """Promotes ``version``, loaded first when the fleet serves its lineage (422 if it cannot be
        served); its robots move to it at their next episode (``PolicySwap.activate_policy``)."""
        self.policies.activate_policy(version, reason)

    # -- metrics (``server.fleet_metrics``) ----------------------------------------------------------------
    def metrics(self) -> dict:
        """Fleet metrics; the episode totals come from one aggregate query, outside the fleet lock."""
        return fleet_metrics(self)

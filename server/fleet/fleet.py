"""``Fleet``: the fleet's robots and the parts that run them, put together; what the API calls (``FleetPort``).

``Fleet`` builds the robots from the settings and composes the parts, each the one owner of its state:

- ``ControlLoop`` (``server.fleet.loop``): the control tick, its thread and its counters;
- ``Lifecycle`` (``server.fleet.lifecycle``): a robot's worker, episodes and takeovers, the transitions
  both the loop and the operators make;
- ``OperatorActions`` (``server.fleet.operators``): claims, commands, pauses, resets and the views;
- ``Recorder`` (``server.fleet.recording``): the rows and files written, with its per-robot state;
- ``PolicySwap`` (``server.fleet.policy_swap``): which loaded policy version each lineage serves;
- ``AssistanceQueue`` and ``OperatorClock`` (``server.fleet.metrics``): requests, leases and the
  operators' time, reported by ``metrics``;
- ``CameraFeed`` (``server.cameras``): the camera views of the robots someone watches, each written into
  the robot's open takeover segment.

It starts and stops two threads (the control loop and the policy registry's watcher). One
re-entrant lock (``Fleet.lock``) guards the robots: a tick holds it, and so does each action that
changes a robot, except heartbeats and teleop commands, which never wait for a tick in progress.
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch
from sqlalchemy.orm import sessionmaker

from server import registry
from server.cameras import CameraFeed, CameraImages, CameraView
from server.fleet.assistance import AssistanceQueue, AssistanceRequest
from server.fleet.inbox import Inbox
from server.fleet.lifecycle import Lifecycle
from server.fleet.loop import ControlLoop
from server.fleet.metrics import MetricsReport, OperatorClock, report
from server.fleet.operators import OperatorActions
from server.fleet.policy_swap import PolicySwap
from server.fleet.recording import Recorder
from server.fleet.robot import Robot, RobotView
from server.fleet.slots import PolicySlot
from server.settings import Settings
from server.workers import WORKERS, WorkerFactory
from sim.registry import make_task
from sim.spaces import TeleopCommand


class Fleet:
    """workers: how robots are started (default: the settings' ``worker`` back end)."""

    def __init__(self, settings: Settings, sessions: sessionmaker, workers: WorkerFactory | None = None) -> None:
        self.settings = settings
        self.sessions = sessions
        self.queue = AssistanceQueue(settings.lease_seconds, settings.queue_order)
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
        self.operator_clock = OperatorClock()
        # how robots are started (the back end); public for the benchmarks, which read its overheads
        self.worker_factory = workers if workers is not None else WORKERS[settings.worker](settings)
        self.lifecycle = Lifecycle(self.recorder, self.queue, self.policies, self.worker_factory, self.operator_clock)
        self.loop = ControlLoop(settings, self.robots, self.lock, self.queue, self.recorder, self.lifecycle)
        self.operators = OperatorActions(
            self.robots, self.lock, self.queue, self.lifecycle, self.operator_clock, lambda: self.loop.running
        )
        self.cameras = CameraFeed(
            self._camera_frame,
            self._record_images,
            settings.camera_hz,
            (settings.camera_width, settings.camera_height),
            enabled=settings.cameras,
            gl=settings.camera_gl,
        )
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._watcher: threading.Thread | None = None
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
                self.robots[rid] = Robot(rid, group.task, slot, self.settings.seed + 1000 * rid, Inbox(limits))
                rid += 1

    def spawn_workers(self) -> None:
        """Starts every robot's worker and first episode (``start`` does, before its threads)."""
        for robot in self.robots.values():
            self.lifecycle.spawn(robot)

    def start(self) -> None:
        # the physics workers keep the cores busy: intra-op threads in the server only contend with them
        torch.set_num_threads(self.settings.torch_threads)
        self.spawn_workers()
        self._thread = threading.Thread(target=self.loop.run, args=(self._stop,), name="fleet-control", daemon=True)
        self._thread.start()
        self._watcher = threading.Thread(
            target=self.policies.watch, args=(self._stop,), name="fleet-registry", daemon=True
        )
        self._watcher.start()

    def stop(self) -> None:
        """Finishes the current tick, closes open takeovers and episodes, stops the workers."""
        self._stop.set()
        self.cameras.close()
        if self._thread is not None:
            self._thread.join(timeout=30)
        if self._watcher is not None:
            self._watcher.join(timeout=30)
        with self.lock:
            for robot in self.robots.values():
                self.lifecycle.interrupt(robot, "stopped", "service-stopped")
                if robot.worker is not None:
                    robot.worker.close()
            for robot in self.robots.values():
                if robot.worker is not None:
                    robot.worker.join(timeout=5)
            served = {id(s): s for s in [*(r.slot for r in self.robots.values()), *self.slots.values()]}
            for slot in served.values():
                slot.controller.inference.close()  # an inference actor, if the slot has one

    def tick(self) -> bool:
        """One control tick under the fleet lock (the loop thread's, or a test's that drives ticks by hand)."""
        with self.lock:
            return self.loop.tick()

    # -- FleetPort ----------------------------------------------------------------------------------------
    @property
    def ticks(self) -> int:
        return self.loop.ticks

    @property
    def data_dir(self) -> Path:
        return self.settings.data_dir

    @property
    def remote(self) -> bool:
        """The fleet runs in this process: its calls never cross to another."""
        return False

    def view(self, robot_id: int) -> RobotView:
        return self.operators.view(robot_id)

    def views(self) -> list[RobotView]:
        return self.operators.views()

    def camera_view(self, robot_id: int) -> CameraView:
        """The robot's latest camera views (``server.cameras``); asking marks it watched. 404 for an unknown robot."""
        self.operators.view(robot_id)
        return self.cameras.view(robot_id)

    def _camera_frame(self, robot_id: int):
        view = self.operators.view(robot_id)
        return view.task, view.frame

    def _record_images(self, images: CameraImages) -> None:
        """Views rendered while the robot is under teleop go into its open takeover segment."""
        with self.lock:
            robot = self.robots.get(images.robot_id)
            if robot is not None:
                self.recorder.takeover_images(robot, images)

    def requests(self) -> list[AssistanceRequest]:
        return self.operators.requests()

    def request_help(self, robot_id: int, reason: str) -> None:
        self.operators.request_help(robot_id, reason)

    def claim(self, robot_id: int, operator: str) -> AssistanceRequest:
        return self.operators.claim(robot_id, operator)

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest:
        return self.operators.heartbeat(robot_id, operator)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        return self.operators.command(robot_id, operator, command)

    def release(self, robot_id: int, operator: str) -> None:
        self.operators.release(robot_id, operator)

    def pause(self, robot_id: int) -> None:
        self.operators.pause(robot_id)

    def resume(self, robot_id: int) -> None:
        self.operators.resume(robot_id)

    def reset(self, robot_id: int) -> None:
        self.operators.reset(robot_id)

    # -- policy versions (``server.fleet.policy_swap``) -------------------------------------------------------
    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int:
        """Adds a policy folder as a ``candidate`` version (idempotent by path); returns its id."""
        return self.policies.register_policy(path, task, parent)

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]:
        """The registry's lineages with their active version and last fine-tuning job, at most
        ``max_age`` seconds old."""
        return self.policies.lineages(max_age)

    def sync_policies(self) -> list[int]:
        """Assigns each served lineage the registry's active version (loaded first); returns the versions
        newly assigned (``PolicySwap.sync_policies``)."""
        return self.policies.sync_policies()

    def activate_policy(self, version: int, reason: str | None = None) -> None:
        """Promotes ``version``, loaded first when the fleet serves its lineage (422 if it cannot be
        served); its robots move to it at their next episode (``PolicySwap.activate_policy``)."""
        self.policies.activate_policy(version, reason)

    # -- metrics ------------------------------------------------------------------------------------------
    def metrics(self) -> MetricsReport:
        """Fleet metrics; the episode totals come from one aggregate query, outside the fleet lock."""
        return report(self.recorder.totals(), self.queue, self.operator_clock, self.views(), self.ticks)

"""``Fleet``: the fleet's robots and the parts that run them, put together; what the API calls (``FleetPort``).

``Fleet`` builds the robots from the settings and composes the parts, each the one owner of its state:

- ``ControlLoop`` (``server.fleet.loop``): the control tick, its thread and its counters;
- ``Lifecycle`` (``server.fleet.lifecycle``): a robot's worker, episodes and takeovers, the transitions
  both the loop and the operators make;
- ``Recorder`` (``server.fleet.recording``): the rows and files written, with its per-robot state;
- ``PolicySwap`` (``server.fleet.policy_swap``): which loaded policy version each lineage serves;
- ``AssistanceQueue`` and ``OperatorClock`` (``server.fleet.metrics``): requests, leases and the
  operators' time, reported by ``metrics``;
- ``CameraFeed`` (``server.cameras``): the camera views of the robots someone watches, each written into
  the robot's open takeover segment.

``Fleet`` itself is what operators, admins and the consoles do (``FleetPort``). No action changes a robot
itself: each puts what it asks in the robot's inbox (``server.fleet.inbox``), which the control loop
applies at the start of its next tick, the one writer of a robot's control state (``policy.hitl_state``).
Claims, releases, heartbeats and commands are decided in the assistance queue under its own lock and
never wait for a tick; an admin's pause, resume, reset or request for help waits for the tick that
applies it and answers from there. Readers see each robot as the loop last published it
(``Robot.publish``).

It starts and stops two threads (the control loop and the policy registry's watcher). One
re-entrant lock (``Fleet.lock``) guards the robots: a tick holds it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch
from sqlalchemy.orm import sessionmaker

from policy.hitl_state import Mode
from server import registry
from server.cameras import CameraFeed, CameraImages, CameraView
from server.errors import ServiceError
from server.fleet.assistance import AskRecord, AssistanceQueue, AssistanceRequest
from server.fleet.inbox import Handover, Inbox, Ticket
from server.fleet.lifecycle import Lifecycle
from server.fleet.loop import ControlLoop
from server.fleet.metrics import MetricsReport, OperatorClock, report
from server.fleet.policy_swap import PolicySwap
from server.fleet.recording import Recorder
from server.fleet.robot import Robot, RobotView
from server.fleet.slots import PolicySlot
from server.settings import Settings
from server.workers import WORKERS, WorkerFactory, WorkerFault
from sim.registry import make_task
from sim.spaces import TeleopCommand

COMMANDABLE = (Mode.WAITING, Mode.TELEOP)  # a holder's commands wait for the claim's tick, or drive


class Fleet:
    """workers: how robots are started (default: the settings' ``worker`` back end)."""

    def __init__(self, settings: Settings, sessions: sessionmaker, workers: WorkerFactory | None = None) -> None:
        self.settings = settings
        self.sessions = sessions
        self.queue = AssistanceQueue(settings.queue.lease_seconds, settings.queue.order)
        self.recorder = Recorder(
            sessions,
            settings.data_dir,
            settings.recording.episodes,
            settings.recording.flush_seconds,
            settings.recording.fsync,
        )
        self.robots: dict[int, Robot] = {}
        self.lock = threading.RLock()
        self.policies = PolicySwap(settings, sessions, self.lock, self.robots)  # slots, and the lineages' versions
        self.operator_clock = OperatorClock()
        # how robots are started (the back end); public for the benchmarks, which read its overheads
        self.worker_factory = workers if workers is not None else WORKERS[settings.workers.kind](settings)
        self.lifecycle = Lifecycle(self.recorder, self.queue, self.policies, self.worker_factory, self.operator_clock)
        self.loop = ControlLoop(settings, self.robots, self.lock, self.queue, self.recorder, self.lifecycle)
        self.cameras = CameraFeed(
            self._camera_frame,
            self._record_images,
            settings.cameras.hz,
            (settings.cameras.width, settings.cameras.height),
            enabled=settings.cameras.enabled,
            gl=settings.cameras.gl,
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
        torch.set_num_threads(self.settings.inference.torch_threads)
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
        """The robot as the loop last published it; ``ServiceError`` 404 for an unknown robot."""
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                robot.publish()
        return robot.view

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    def robot(self, robot_id: int) -> Robot:
        robot = self.robots.get(robot_id)
        if robot is None:
            raise ServiceError(404, f"no robot {robot_id}")
        return robot

    def camera_view(self, robot_id: int) -> CameraView:
        """The robot's latest camera views (``server.cameras``); asking marks it watched. 404 for an unknown robot."""
        self.robot(robot_id)
        return self.cameras.view(robot_id)

    def _camera_frame(self, robot_id: int):
        view = self.view(robot_id)
        return view.task, view.frame

    def _record_images(self, images: CameraImages) -> None:
        """Views rendered while the robot is under teleop go into its open takeover segment."""
        with self.lock:
            robot = self.robots.get(images.robot_id)
            if robot is not None:
                self.recorder.takeover_images(robot, images)

    def requests(self) -> list[AssistanceRequest]:
        """Open assistance requests, unclaimed first, by priority (the queue's own lock)."""
        return self.queue.pending()

    # -- an operator's (never waits for a tick) -----------------------------------------------------------
    def claim(self, robot_id: int, operator: str) -> AssistanceRequest:
        """Gives ``operator`` the robot's lease (the queue decides, under its own lock), and waits for the
        loop's next tick to put the robot under their control."""
        robot = self.robot(robot_id)
        before = self.queue.get(robot_id)
        previous = before.holder if before is not None else None
        req = self.queue.claim(robot_id, operator)
        self.operator_clock.claimed(operator)
        if previous is not None and previous != operator:
            robot.inbox.drop_commands()  # the previous holder's lease ran out: none of their commands is applied
        self._deliver(robot, Handover("claim", operator))
        return req

    def release(self, robot_id: int, operator: str) -> None:
        """Hands the robot back at the loop's next tick, and waits for it; from now on the operator's
        commands are refused."""
        robot = self.robot(robot_id)
        self.queue.release(robot_id, operator)
        self._deliver(robot, Handover("release", operator))

    def _deliver(self, robot: Robot, handover: Handover) -> None:
        """Puts ``handover`` in the robot's inbox and, while the loop runs, waits for the tick that applies
        it (``HANDOVER_WAIT_S`` at most), so that the caller's next request sees it. With no loop running
        (ticks driven by hand) the next tick applies it."""
        robot.inbox.put(handover)
        if self.loop.running:
            handover.wait()

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest:
        """Renews the lease; the queue has its own lock, so this never waits for a tick in progress."""
        self.robot(robot_id)
        return self.queue.heartbeat(robot_id, operator)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        """Accepts a command for the tick that next steps the robot under the holder's control, without
        waiting for a tick in progress. Commands arriving between ticks compose (``server.fleet.commands``):
        returns how many that tick applies; 429 when the composition would exceed the per-step limits. An
        accepted command renews the operator's lease, as a heartbeat does: an operator who is driving is there."""
        robot = self.robot(robot_id)
        if (mode := robot.mode) not in COMMANDABLE:
            raise ServiceError(409, f"robot {robot_id} is {mode}, not under teleop")
        self.queue.check_holder(robot_id, operator)
        pending = robot.inbox.command(command)
        try:  # renews the lease, and sees whether control went back while the command was being put
            self.queue.heartbeat(robot_id, operator)
        except ServiceError:
            robot.inbox.drop_commands()  # nothing in the inbox of a robot not under teleop is ever applied
            raise
        return pending

    # -- an admin's (waits for the tick that applies it) -----------------------------------------------------
    def _admin(self, robot_id: int, action: Callable[[Robot], object]) -> object:
        robot = self.robot(robot_id)
        ticket = Ticket(lambda: action(robot))
        robot.inbox.put(ticket)
        if not self.loop.running:  # no loop thread (before the start, a test's ticks): apply it here
            with self.lock:
                self.lifecycle.apply_inbox(robot)
        return ticket.answer()

    def request_help(self, robot_id: int, reason: str) -> None:
        """Puts an autonomous robot in ``waiting`` as if its signal had asked: drills of the queue and the
        console that need no signal to ask (``hitl bench`` uses it)."""

        def ask(robot: Robot) -> None:
            if robot.mode != Mode.AUTONOMOUS or robot.frame is None:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not autonomous with a frame")
            robot.slot.controller.ask(robot.id, robot.frame.hold)
            robot.events += 1
            robot.ask = self.queue.ask(robot.id, AskRecord.requested(reason, robot.frame)).ask

        self._admin(robot_id, ask)

    def pause(self, robot_id: int) -> None:
        def pause(robot: Robot) -> None:
            if robot.mode == Mode.FAULTED:
                raise ServiceError(409, f"robot {robot_id} is faulted")
            robot.control.pause()

        self._admin(robot_id, pause)

    def resume(self, robot_id: int) -> None:
        def resume(robot: Robot) -> None:
            if robot.mode != Mode.PAUSED:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not paused")
            back = robot.control.resume()
            req = self.queue.get(robot_id)
            if back == Mode.TELEOP and (req is None or req.holder is None):  # the lease ran out while paused
                back = Mode.WAITING if req is not None else Mode.AUTONOMOUS
            controller = robot.slot.controller
            if robot.id in controller:
                if back == Mode.WAITING and robot.frame is not None:
                    controller.ask(robot.id, robot.frame.hold)
                elif back == Mode.AUTONOMOUS and robot.mode != Mode.AUTONOMOUS:
                    controller.release(robot.id)

        self._admin(robot_id, resume)

    def reset(self, robot_id: int) -> None:
        def reset(robot: Robot) -> None:
            if robot.mode == Mode.FAULTED:
                raise ServiceError(409, f"robot {robot_id} is faulted; it restarts by itself")
            self.lifecycle.interrupt(robot, "reset", "reset")
            if robot.worker.busy:  # the answer to the step in flight is dropped
                deadline = time.monotonic() + 10
                try:
                    while robot.worker.poll() is None and time.monotonic() < deadline:
                        time.sleep(0.001)
                except WorkerFault as exc:
                    self.lifecycle.fault(robot, str(exc))
                    return
            if robot.mode == Mode.PAUSED:  # a reset also ends a pause
                robot.control.resume()
            self.lifecycle.new_episode(robot)

        self._admin(robot_id, reset)

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

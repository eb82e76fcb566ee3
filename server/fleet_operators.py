"""The fleet's service methods: what operators, admins and the consoles call (claim, command, pause, views...).

Each method takes the fleet lock for what it changes, except those that must never wait for a tick in
progress: ``heartbeat`` and ``command`` go through the assistance queue's and the command mailbox's own
locks. A robot's published view (``Robot.publish``) is renewed after each change, so readers see it at
once rather than at the next tick.

A mixin of ``server.fleet.Fleet``, which holds the state it works on (the attributes annotated on
``OperatorMethods``); ending a takeover or an episode goes through the control loop's transitions
(``server.fleet_loop.ControlLoop``: ``_hand_back``, ``_interrupt``, ``_fault``, ``_new_episode``), which
the fleet provides.
"""

from __future__ import annotations

import threading
import time

from policy.controller import Mode
from server.assistance import AssistanceQueue
from server.errors import ServiceError
from server.recording import Recorder
from server.robot import Robot, RobotView
from server.workers import WorkerFault
from sim.spaces import TeleopCommand


class OperatorMethods:
    """Claims, commands, releases, pauses and resets of one robot, and the views readers see."""

    queue: AssistanceQueue
    recorder: Recorder
    robots: dict[int, Robot]
    lock: threading.RLock
    operator_since: dict[str, float]

    # -- what readers see -------------------------------------------------------------------------------------
    def view(self, robot_id: int) -> RobotView:
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                robot.publish()
        return robot.view

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    # -- service methods (the API calls these) ---------------------------------------------------------------
    def robot(self, robot_id: int) -> Robot:
        robot = self.robots.get(robot_id)
        if robot is None:
            raise ServiceError(404, f"no robot {robot_id}")
        return robot

    def request_help(self, robot_id: int, reason: str) -> None:
        """Puts an autonomous robot in ``waiting`` as if its signal had asked (benchmarks, drills)."""
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode != "autonomous" or robot.frame is None:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not autonomous with a frame")
            robot.slot.controller.ask(robot.id, robot.frame.hold)
            robot.mode = "waiting"
            robot.events += 1
            self.queue.open(robot.id, 1.0, 1.0, reason)
            robot.publish()

    def claim(self, robot_id: int, operator: str):
        with self.lock:
            robot = self.robot(robot_id)
            req = self.queue.claim(robot_id, operator)
            self.operator_since.setdefault(operator, time.monotonic())
            if robot.segment is not None and robot.segment.meta.get("operator") != operator:
                # the previous holder's lease ran out before a tick expired it: their takeover is over
                self.recorder.close_segment(robot, "lease-expired")
                robot.commands.clear()
                if robot.mode == "teleop":
                    self.recorder.open_segment(robot, operator, req.reason)
            if robot.mode == "waiting":
                robot.slot.controller.take_over(robot.id)
                robot.teleop_left = robot.slot.controller.teleop_left(robot.id)
                robot.mode = "teleop"
                robot.commands.clear()
                if robot.segment is None:
                    self.recorder.open_segment(robot, operator, req.reason)
            robot.publish()
            return req

    def heartbeat(self, robot_id: int, operator: str):
        """Renews the lease; the queue has its own lock, so this never waits for a tick in progress."""
        self.robot(robot_id)
        return self.queue.heartbeat(robot_id, operator)

    def release(self, robot_id: int, operator: str) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self.queue.check_holder(robot_id, operator)
            self._hand_back(robot)
            robot.publish()

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        """Accepts a command for the next tick without waiting for a tick in progress (no fleet lock).
        Commands arriving between ticks compose (``server.commands``): returns how many the next tick
        applies; 429 when the composition would exceed the per-step limits. An accepted command renews
        the operator's lease, as a heartbeat does: an operator who is driving is there."""
        robot = self.robot(robot_id)
        if robot.mode != "teleop":
            raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not under teleop")
        self.queue.check_holder(robot_id, operator)
        pending = robot.commands.put(command)
        try:  # renews the lease, and sees whether control went back while the command was being put
            self.queue.heartbeat(robot_id, operator)
        except ServiceError:
            robot.commands.clear()  # nothing in the mailbox of a robot not under teleop is ever applied
            raise
        if robot.mode != "teleop":
            robot.commands.clear()
            raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not under teleop")
        return pending

    def pause(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode == "faulted":
                raise ServiceError(409, f"robot {robot_id} is faulted")
            if robot.mode != "paused":
                robot.paused_from, robot.mode = robot.mode, "paused"
            robot.publish()

    def resume(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode != "paused":
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not paused")
            back = robot.paused_from if robot.paused_from in ("waiting", "teleop") else "autonomous"
            req = self.queue.get(robot_id)
            if back == "teleop" and (req is None or req.holder is None):  # the lease ran out while paused
                back = "waiting" if req is not None else "autonomous"
            controller = robot.slot.controller
            if robot.id in controller:
                if back == "waiting" and robot.frame is not None:
                    controller.ask(robot.id, robot.frame.hold)
                elif back == "autonomous" and controller.mode(robot.id) != Mode.AUTONOMOUS:
                    controller.release(robot.id)
            robot.mode, robot.paused_from = back, None
            robot.publish()

    def reset(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode == "faulted":
                raise ServiceError(409, f"robot {robot_id} is faulted; it restarts by itself")
            self._interrupt(robot, "reset", "reset")
            if robot.worker.busy:  # the answer to the step in flight is dropped
                deadline = time.monotonic() + 10
                try:
                    while robot.worker.poll() is None and time.monotonic() < deadline:
                        time.sleep(0.001)
                except WorkerFault as exc:
                    self._fault(robot, str(exc))
                    robot.publish()
                    return
            robot.mode = "autonomous"
            self._new_episode(robot)
            robot.publish()

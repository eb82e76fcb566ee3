"""The fleet's service methods: what operators, admins and the consoles call (claim, command, pause, views...).

Each method takes the fleet lock for what it changes, except those that must never wait for a tick in
progress: ``heartbeat`` and ``command`` go through the assistance queue's and the command mailbox's own
locks, and ``claim`` and ``release`` through the queue's and the robot's handover mailbox, which the
loop applies at its next tick (``server.handovers``). A robot's published view (``Robot.publish``) is
renewed after each change, and shown with its pending handovers, so readers see a change at once
rather than at the next tick.

A mixin of ``server.fleet.Fleet``, which holds the state it works on (the attributes annotated on
``OperatorMethods``); ending a takeover or an episode goes through the control loop's transitions
(``server.fleet_loop.ControlLoop``: ``_hand_back``, ``_interrupt``, ``_fault``, ``_new_episode``), which
the fleet provides.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

from policy.controller import Mode
from server.assistance import AssistanceQueue, AssistanceRequest
from server.errors import ServiceError
from server.handovers import Handover
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
        """The robot as published, in the mode its pending claims and releases give it (``server.handovers``)."""
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                robot.publish()
        pending = robot.handovers.pending()  # before the view: each handover is in one or the other
        view = robot.view
        shown = robot.handovers.shown_mode(view.mode, pending)
        return view if shown == view.mode else replace(view, mode=shown, teleop_left=None)

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    def requests(self) -> list[AssistanceRequest]:
        """Open assistance requests, unclaimed first, by priority (the queue's own lock)."""
        return self.queue.pending()

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
            self._apply_handovers(robot)
            if robot.mode != "autonomous" or robot.frame is None:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not autonomous with a frame")
            robot.slot.controller.ask(robot.id, robot.frame.hold)
            robot.mode = "waiting"
            robot.events += 1
            self.queue.open(robot.id, 1.0, 1.0, reason)
            robot.publish()

    def claim(self, robot_id: int, operator: str):
        """Gives ``operator`` the robot's lease now (the queue decides, under its own lock); the loop puts
        the robot under their control at its next tick (``server.handovers``), without this call waiting
        for the tick in progress."""
        robot = self.robot(robot_id)
        before = self.queue.get(robot_id)
        previous = before.holder if before is not None else None
        req = self.queue.claim(robot_id, operator)
        self.operator_since.setdefault(operator, time.monotonic())
        if previous is not None and previous != operator:
            robot.commands.clear()  # the previous holder's lease ran out: none of their commands is applied
        robot.handovers.put(Handover("claim", operator))
        return req

    def release(self, robot_id: int, operator: str) -> None:
        """Hands the robot back at the loop's next tick (``server.handovers``); from now on it is shown
        handed back and the operator's commands are refused."""
        robot = self.robot(robot_id)
        self.queue.check_holder(robot_id, operator)
        robot.handovers.put(Handover("release", operator))

    def _apply_handovers(self, robot: Robot) -> None:
        """The robot's claims and releases accepted since they were last applied, in order, each only if
        the queue still has its operator holding the robot. Under the fleet lock: by the loop before it
        steps, and by every other method that changes the robot before it does (a claim accepted before
        a reset is a takeover that the reset ends)."""
        handovers = robot.handovers.pending()
        for h in handovers:
            req = self.queue.get(robot.id)
            if req is None or req.holder != h.operator:  # the request ended or the lease ran out meanwhile
                continue
            if h.kind == "claim":
                self._take_over(robot, h.operator, req.reason)
            else:
                self._hand_back(robot)
        if handovers:
            robot.publish()
            robot.handovers.applied(len(handovers))

    def _take_over(self, robot: Robot, operator: str, reason: str) -> None:
        if robot.segment is not None and robot.segment.meta.get("operator") != operator:
            # the previous holder's lease ran out before a tick expired it: their takeover is over
            self.recorder.close_segment(robot, "lease-expired")
            if robot.mode == "teleop":
                self.recorder.open_segment(robot, operator, reason)
        if robot.mode == "waiting":
            robot.slot.controller.take_over(robot.id)
            robot.teleop_left = robot.slot.controller.teleop_left(robot.id)
            robot.mode = "teleop"
            if robot.segment is None:
                self.recorder.open_segment(robot, operator, reason)

    def heartbeat(self, robot_id: int, operator: str):
        """Renews the lease; the queue has its own lock, so this never waits for a tick in progress."""
        self.robot(robot_id)
        return self.queue.heartbeat(robot_id, operator)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        """Accepts a command for the next tick without waiting for a tick in progress (no fleet lock).
        Commands arriving between ticks compose (``server.commands``): returns how many the next tick
        applies; 429 when the composition would exceed the per-step limits. An accepted command renews
        the operator's lease, as a heartbeat does: an operator who is driving is there."""
        robot = self.robot(robot_id)
        if (mode := robot.handovers.shown_mode(robot.mode)) != "teleop":
            raise ServiceError(409, f"robot {robot_id} is {mode}, not under teleop")
        self.queue.check_holder(robot_id, operator)
        pending = robot.commands.put(command)
        try:  # renews the lease, and sees whether control went back while the command was being put
            self.queue.heartbeat(robot_id, operator)
        except ServiceError:
            robot.commands.clear()  # nothing in the mailbox of a robot not under teleop is ever applied
            raise
        if (mode := robot.handovers.shown_mode(robot.mode)) != "teleop":
            robot.commands.clear()
            raise ServiceError(409, f"robot {robot_id} is {mode}, not under teleop")
        return pending

    def pause(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self._apply_handovers(robot)
            if robot.mode == "faulted":
                raise ServiceError(409, f"robot {robot_id} is faulted")
            if robot.mode != "paused":
                robot.paused_from, robot.mode = robot.mode, "paused"
            robot.publish()

    def resume(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self._apply_handovers(robot)
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
            self._apply_handovers(robot)
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

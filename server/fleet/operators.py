"""What operators, admins and the consoles do to the fleet's robots (claim, command, pause, views...).

Each action takes the fleet lock for what it changes, except those that must never wait for a tick in
progress: ``heartbeat`` and ``command`` go through the assistance queue's and the command mailbox's own
locks, and ``claim`` and ``release`` through the queue's and the robot's handover mailbox, which the
loop applies at its next tick (``server.fleet.handovers``). A robot's published view (``Robot.publish``)
is renewed after each change, and shown with its pending handovers, so readers see a change at once
rather than at the next tick. Ending a takeover or an episode goes through the robot's lifecycle
(``server.fleet.lifecycle``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

from policy.controller import Mode
from server.errors import ServiceError
from server.fleet.assistance import AskRecord, AssistanceQueue, AssistanceRequest
from server.fleet.handovers import Handover
from server.fleet.lifecycle import Lifecycle
from server.fleet.metrics import OperatorClock
from server.fleet.modes import FleetMode
from server.fleet.robot import Robot, RobotView
from server.workers import WorkerFault
from sim.spaces import TeleopCommand

RESUMABLE = (FleetMode.WAITING, FleetMode.TELEOP)  # what a paused robot resumes into; else autonomous


class OperatorActions:
    """Claims, commands, releases, pauses and resets of one robot, and the views readers see."""

    def __init__(
        self,
        robots: dict[int, Robot],
        lock: threading.RLock,
        queue: AssistanceQueue,
        lifecycle: Lifecycle,
        clock: OperatorClock,
    ) -> None:
        self.robots = robots
        self.lock = lock
        self.queue = queue
        self.lifecycle = lifecycle
        self.clock = clock

    # -- what readers see -------------------------------------------------------------------------------------
    def view(self, robot_id: int) -> RobotView:
        """The robot as published, in the mode its pending claims and releases give it (``server.fleet.handovers``):
        one shown handed back shows no request either."""
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                robot.publish()
        pending = robot.handovers.pending()  # before the view: each handover is in one or the other
        view = robot.view
        shown = robot.handovers.shown_mode(view.mode, pending)
        if shown == view.mode:
            return view
        return replace(view, mode=shown, teleop_left=None, ask=view.ask if shown != FleetMode.AUTONOMOUS else None)

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    def requests(self) -> list[AssistanceRequest]:
        """Open assistance requests, unclaimed first, by priority (the queue's own lock)."""
        return self.queue.pending()

    # -- actions (the API calls these) ------------------------------------------------------------------------
    def robot(self, robot_id: int) -> Robot:
        robot = self.robots.get(robot_id)
        if robot is None:
            raise ServiceError(404, f"no robot {robot_id}")
        return robot

    def request_help(self, robot_id: int, reason: str) -> None:
        """Puts an autonomous robot in ``waiting`` as if its signal had asked (benchmarks, drills)."""
        with self.lock:
            robot = self.robot(robot_id)
            self.lifecycle.apply_handovers(robot)
            if robot.mode != FleetMode.AUTONOMOUS or robot.frame is None:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not autonomous with a frame")
            robot.slot.controller.ask(robot.id, robot.frame.hold)
            robot.set_mode(FleetMode.WAITING)
            robot.events += 1
            robot.ask = self.queue.ask(robot.id, AskRecord.requested(reason, robot.frame)).ask
            robot.publish()

    def claim(self, robot_id: int, operator: str):
        """Gives ``operator`` the robot's lease now (the queue decides, under its own lock); the loop puts
        the robot under their control at its next tick (``server.fleet.handovers``), without this call waiting
        for the tick in progress."""
        robot = self.robot(robot_id)
        before = self.queue.get(robot_id)
        previous = before.holder if before is not None else None
        req = self.queue.claim(robot_id, operator)
        self.clock.claimed(operator)
        if previous is not None and previous != operator:
            robot.commands.clear()  # the previous holder's lease ran out: none of their commands is applied
        robot.handovers.put(Handover("claim", operator))
        return req

    def release(self, robot_id: int, operator: str) -> None:
        """Hands the robot back at the loop's next tick (``server.fleet.handovers``); from now on it is shown
        handed back and the operator's commands are refused."""
        robot = self.robot(robot_id)
        self.queue.check_holder(robot_id, operator)
        robot.handovers.put(Handover("release", operator))

    def heartbeat(self, robot_id: int, operator: str):
        """Renews the lease; the queue has its own lock, so this never waits for a tick in progress."""
        self.robot(robot_id)
        return self.queue.heartbeat(robot_id, operator)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        """Accepts a command for the next tick without waiting for a tick in progress (no fleet lock).
        Commands arriving between ticks compose (``server.fleet.commands``): returns how many the next tick
        applies; 429 when the composition would exceed the per-step limits. An accepted command renews
        the operator's lease, as a heartbeat does: an operator who is driving is there."""
        robot = self.robot(robot_id)
        if (mode := robot.handovers.shown_mode(robot.mode)) != FleetMode.TELEOP:
            raise ServiceError(409, f"robot {robot_id} is {mode}, not under teleop")
        self.queue.check_holder(robot_id, operator)
        pending = robot.commands.put(command)
        try:  # renews the lease, and sees whether control went back while the command was being put
            self.queue.heartbeat(robot_id, operator)
        except ServiceError:
            robot.commands.clear()  # nothing in the mailbox of a robot not under teleop is ever applied
            raise
        if (mode := robot.handovers.shown_mode(robot.mode)) != FleetMode.TELEOP:
            robot.commands.clear()
            raise ServiceError(409, f"robot {robot_id} is {mode}, not under teleop")
        return pending

    def pause(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self.lifecycle.apply_handovers(robot)
            if robot.mode == FleetMode.FAULTED:
                raise ServiceError(409, f"robot {robot_id} is faulted")
            robot.pause()
            robot.publish()

    def resume(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self.lifecycle.apply_handovers(robot)
            if robot.mode != FleetMode.PAUSED:
                raise ServiceError(409, f"robot {robot_id} is {robot.mode}, not paused")
            back = robot.paused_from if robot.paused_from in RESUMABLE else FleetMode.AUTONOMOUS
            req = self.queue.get(robot_id)
            if back == FleetMode.TELEOP and (req is None or req.holder is None):  # the lease ran out while paused
                back = FleetMode.WAITING if req is not None else FleetMode.AUTONOMOUS
            controller = robot.slot.controller
            if robot.id in controller:
                if back == FleetMode.WAITING and robot.frame is not None:
                    controller.ask(robot.id, robot.frame.hold)
                elif back == FleetMode.AUTONOMOUS and controller.mode(robot.id) != Mode.AUTONOMOUS:
                    controller.release(robot.id)
            robot.resume(back)
            robot.publish()

    def reset(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self.lifecycle.apply_handovers(robot)
            if robot.mode == FleetMode.FAULTED:
                raise ServiceError(409, f"robot {robot_id} is faulted; it restarts by itself")
            self.lifecycle.interrupt(robot, "reset", "reset")
            if robot.worker.busy:  # the answer to the step in flight is dropped
                deadline = time.monotonic() + 10
                try:
                    while robot.worker.poll() is None and time.monotonic() < deadline:
                        time.sleep(0.001)
                except WorkerFault as exc:
                    self.lifecycle.fault(robot, str(exc))
                    robot.publish()
                    return
            robot.resume(FleetMode.AUTONOMOUS)  # a reset also ends a pause
            self.lifecycle.new_episode(robot)
            robot.publish()

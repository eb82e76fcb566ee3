"""What operators, admins and the consoles do to the fleet's robots (claim, command, pause, views...).

No action changes a robot itself: each puts what it asks in the robot's inbox (``server.fleet.inbox``),
which the control loop applies at the start of its next tick, the one writer of a robot's control state
(``policy.hitl_state``). Claims, releases, heartbeats and commands are decided in the assistance queue
under its own lock and never wait for a tick; an admin's pause, resume, reset or request for help waits
for the tick that applies it and answers from there. Readers see each robot as the loop last published
it (``Robot.publish``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from policy.hitl_state import Mode
from server.errors import ServiceError
from server.fleet.assistance import AskRecord, AssistanceQueue, AssistanceRequest
from server.fleet.inbox import Handover, Ticket
from server.fleet.lifecycle import Lifecycle
from server.fleet.metrics import OperatorClock
from server.fleet.robot import Robot, RobotView
from server.workers import WorkerFault
from sim.spaces import TeleopCommand

COMMANDABLE = (Mode.WAITING, Mode.TELEOP)  # a holder's commands wait for the claim's tick, or drive


class OperatorActions:
    """Claims, commands, releases, pauses and resets of one robot, and the views readers see. loop_running:
    whether the control loop's thread applies the inboxes (else an action applies its robot's itself)."""

    def __init__(
        self,
        robots: dict[int, Robot],
        lock: threading.RLock,
        queue: AssistanceQueue,
        lifecycle: Lifecycle,
        clock: OperatorClock,
        loop_running: Callable[[], bool],
    ) -> None:
        self.robots = robots
        self.lock = lock
        self.queue = queue
        self.lifecycle = lifecycle
        self.clock = clock
        self.loop_running = loop_running

    # -- what readers see -------------------------------------------------------------------------------------
    def view(self, robot_id: int) -> RobotView:
        """The robot as the loop last published it."""
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                robot.publish()
        return robot.view

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    def requests(self) -> list[AssistanceRequest]:
        """Open assistance requests, unclaimed first, by priority (the queue's own lock)."""
        return self.queue.pending()

    def robot(self, robot_id: int) -> Robot:
        robot = self.robots.get(robot_id)
        if robot is None:
            raise ServiceError(404, f"no robot {robot_id}")
        return robot

    # -- an operator's (never waits for a tick) ---------------------------------------------------------------
    def claim(self, robot_id: int, operator: str) -> AssistanceRequest:
        """Gives ``operator`` the robot's lease now (the queue decides, under its own lock); the loop puts
        the robot under their control at its next tick."""
        robot = self.robot(robot_id)
        before = self.queue.get(robot_id)
        previous = before.holder if before is not None else None
        req = self.queue.claim(robot_id, operator)
        self.clock.claimed(operator)
        if previous is not None and previous != operator:
            robot.inbox.drop_commands()  # the previous holder's lease ran out: none of their commands is applied
        robot.inbox.put(Handover("claim", operator))
        return req

    def release(self, robot_id: int, operator: str) -> None:
        """Hands the robot back at the loop's next tick; from now on the operator's commands are refused."""
        robot = self.robot(robot_id)
        self.queue.release(robot_id, operator)
        robot.inbox.put(Handover("release", operator))

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

    # -- an admin's (waits for the tick that applies it) ------------------------------------------------------
    def _admin(self, robot_id: int, action: Callable[[Robot], object]) -> object:
        robot = self.robot(robot_id)
        ticket = Ticket(lambda: action(robot))
        robot.inbox.put(ticket)
        if not self.loop_running():  # no loop thread (before the start, a test's ticks): apply it here
            with self.lock:
                self.lifecycle.apply_inbox(robot)
        return ticket.answer()

    def request_help(self, robot_id: int, reason: str) -> None:
        """Puts an autonomous robot in ``waiting`` as if its signal had asked (drills of the queue and the
        console without waiting for a signal; ``hitl bench`` uses it)."""

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

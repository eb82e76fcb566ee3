"""A fleet robot's life: its worker, its episodes and its takeovers, one transition per method.

The control loop (``server.fleet.loop``) and the actions it applies from the robots' inboxes both
change a robot through these transitions, always under the fleet lock: a worker is spawned, faults
and restarts with backoff (``RESTART_BACKOFF``); an episode opens on the policy version its lineage is
assigned (``server.fleet.policy_swap``), ends on its own (success, the horizon) or is interrupted (a
fault, a reset, the service stopping); a takeover starts when a claim is applied, and ends with a
hand-back, a lease that ran out, the episode's end or an interruption, each closing its recording,
its assistance request and the operator's time.
"""

from __future__ import annotations

import logging
import time

from policy.hitl_state import Mode
from server.fleet.assistance import AskRecord, AssistanceQueue
from server.fleet.inbox import Handover, Ticket
from server.fleet.metrics import OperatorClock
from server.fleet.policy_swap import PolicySwap
from server.fleet.recording import Recorder
from server.fleet.robot import Robot
from server.workers import Priority, WorkerFactory, WorkerFault
from sim.frame import RobotFrame

log = logging.getLogger("hitl.fleet")

RESTART_BACKOFF = (1.0, 2.0, 5.0, 10.0, 30.0)


class Lifecycle:
    """The transitions of the fleet's robots. workers: how a robot's worker is started; clock: the
    operators' time in control, booked when a takeover ends."""

    def __init__(
        self,
        recorder: Recorder,
        queue: AssistanceQueue,
        policies: PolicySwap,
        workers: WorkerFactory,
        clock: OperatorClock,
    ) -> None:
        self.recorder = recorder
        self.queue = queue
        self.policies = policies
        self.workers = workers
        self.clock = clock

    # -- workers ----------------------------------------------------------------------------------------
    def spawn(self, robot: Robot) -> None:
        """Starts the robot's worker and its first episode; the worker renders the policy's cameras when
        the robot's policy sees them."""
        robot.images = bool(robot.slot.policy.config.cameras)
        robot.worker = self.workers(robot.id, robot.task, images=robot.images)
        robot.worker.prioritize(Priority.BACKGROUND)
        self.new_episode(robot)

    def fault(self, robot: Robot, why: str) -> None:
        """The robot's worker died: its episode is interrupted and the worker restarts after a backoff."""
        log.warning("robot %d faulted: %s", robot.id, why.splitlines()[-1] if why else why)
        self.interrupt(robot, "faulted", "worker-fault")
        robot.slot.controller.remove(robot.id)
        robot.control.fault()
        robot.fault, robot.fresh = why, False
        if robot.worker is not None:
            robot.worker.kill()
        robot.worker = None
        robot.restart_at = time.monotonic() + RESTART_BACKOFF[min(robot.restarts, len(RESTART_BACKOFF) - 1)]
        robot.restarts += 1

    def restart_if_due(self, robot: Robot) -> None:
        """A faulted robot whose backoff has run out gets a new worker."""
        if robot.restart_at is not None and time.monotonic() >= robot.restart_at:
            robot.fault, robot.restart_at = None, None
            robot.control.restart()
            self.spawn(robot)

    # -- episodes ---------------------------------------------------------------------------------------
    def new_episode(self, robot: Robot) -> None:
        """The next episode, on the policy version assigned to the robot's lineage (hot swap)."""
        self.policies.move_to_assigned(robot)
        if robot.worker is not None and bool(robot.slot.policy.config.cameras) != robot.images:
            robot.worker.kill()  # the new version sees otherwise (cameras or state): a worker that observes so
            robot.images = not robot.images
            robot.worker = self.workers(robot.id, robot.task, images=robot.images)
            robot.worker.prioritize(Priority.BACKGROUND)
        robot.seed += 1
        robot.slot.controller.reset(robot.id, robot.seed, robot.control)  # autonomous (a pause holds on)
        robot.steps = robot.assisted_steps = robot.events = 0
        robot.timeline.clear()  # a plot of this episode's steps
        robot.fresh = False  # the last frame stays on view until the reset's arrives
        robot.inbox.drop_commands()
        robot.episode_id = self.recorder.open_episode(robot)
        try:
            robot.worker.request_reset(robot.seed)
        except WorkerFault as exc:
            self.fault(robot, str(exc))

    def end_episode(self, robot: Robot, frame: RobotFrame) -> None:
        """The episode ended on its own: success, or the horizon (never under an operator's hands)."""
        outcome = "success" if frame.success else "timeout"
        self.recorder.close_episode_file(robot, frame.success, frame.t, outcome)
        self.end_takeover(robot, "episode-ended")  # a takeover that reached success (a timeout waits for hand-back)
        robot.control.episode_ended()
        robot.episodes_done += 1
        robot.successes += int(frame.success)
        self.recorder.finish_episode(robot, outcome, frame.clock)
        self.new_episode(robot)

    def interrupt(self, robot: Robot, outcome: str, ended_by: str) -> None:
        """Ends the episode early (fault, reset, shutdown): files and rows closed, request dropped.
        ended_by: why, for a takeover in progress (``db.SEGMENT_ENDS``)."""
        self.end_takeover(robot, ended_by)
        self.recorder.close_episode_file(robot, None, robot.steps, outcome)
        self.recorder.finish_episode(robot, outcome)
        robot.inbox.drop_commands()

    # -- takeovers --------------------------------------------------------------------------------------
    def apply_inbox(self, robot: Robot) -> None:
        """What the API asked of the robot since the loop last looked (``server.fleet.inbox``), in order:
        admin actions, and claims and releases each only if the queue still has its operator holding the
        robot. By the loop at the start of a tick (fleet lock held), before it steps anyone."""
        items = robot.inbox.take()
        try:
            for item in items:
                if isinstance(item, Ticket):
                    item.apply()
                    continue
                req = self.queue.get(robot.id)
                if req is None or req.holder != item.operator:  # the request ended or the lease ran out meanwhile
                    continue
                if item.kind == "claim":
                    self.take_over(robot, item.operator, req.ask)
                else:
                    self.hand_back(robot)
            if items:
                robot.publish()
        finally:
            for item in items:
                if isinstance(item, Handover):
                    item.applied.set()  # its caller answers now, having seen what the tick made of it

    def take_over(self, robot: Robot, operator: str, ask: AskRecord) -> None:
        """``operator`` holds the robot's request (``ask``: its record): a waiting robot goes under their
        control."""
        holder = self.recorder.takeover_operator(robot)
        if holder is not None and holder != operator:
            # the previous holder's lease ran out before a tick expired it: their takeover is over
            self.recorder.close_takeover(robot, "lease-expired")
            if robot.mode == Mode.TELEOP:
                self.recorder.open_takeover(robot, operator, ask)
        if robot.mode == Mode.WAITING:
            robot.slot.controller.take_over(robot.id)
            if self.recorder.takeover_operator(robot) is None:
                self.recorder.open_takeover(robot, operator, ask)

    def hand_back(self, robot: Robot) -> None:
        """Control returns to the policy, which restarts from the next frame with a fresh history (an
        episode past its horizon then ends at that frame: its timeout waited for the hand-back)."""
        self.end_takeover(robot, "hand-back")
        if robot.id in robot.slot.controller:
            robot.slot.controller.release(robot.id)
        robot.inbox.drop_commands()

    def end_takeover(self, robot: Robot, ended_by: str) -> None:
        """Closes the takeover's recording and request, and books the operator's time."""
        self.recorder.close_takeover(robot, ended_by)
        req = self.queue.close(robot.id)
        robot.ask = None
        if req is not None and req.holder and req.claimed_at is not None:
            self.clock.add_busy(req.holder, time.monotonic() - req.claimed_at)

    def expire_leases(self, robots: dict[int, Robot]) -> None:
        """Claims whose lease ran out: the takeover is over, the robot holds and its request is queued again."""
        for req in self.queue.expire():
            if req.expired_holder and req.claimed_at is not None:
                self.clock.add_busy(req.expired_holder, time.monotonic() - req.claimed_at)
            robot = robots.get(req.robot_id)
            if robot is None:
                continue
            self.recorder.close_takeover(robot, "lease-expired")  # paused or not: the takeover is over
            robot.inbox.drop_commands()
            if robot.mode == Mode.TELEOP and robot.frame is not None:
                # (past the horizon, the next frame ends the episode: a timeout waited for this)
                robot.slot.controller.ask(robot.id, robot.frame.hold)

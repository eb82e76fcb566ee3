"""The fleet's control loop: one tick over the robot workers, and the workers' and episodes' lives.

One control tick: collect every worker's latest frame (without waiting on any); for the robots that
are ready (a new frame, not paused), one ``Controller.step`` per policy slot: the policy and every
signal batched across that slot's robots, operator and hold actions sent before the batch is
computed. Workers whose robot is under teleop get the control loop's priority, the others a lower
one (``worker_niceness``): on a machine with fewer cores than robots, the batched policy step must
not queue behind the physics it feeds.

A faulted robot (its worker died) is restarted with backoff (``RESTART_BACKOFF``); an episode that
ends on its own (success or the horizon) is recorded and the next one starts at once, on the version
its lineage is assigned (``server.policy_swap``).

A mixin of ``server.fleet.Fleet``, which holds the state it works on (the attributes annotated on
``ControlLoop``); the operator methods (``server.fleet_operators``) end takeovers and episodes through
its ``_hand_back``, ``_interrupt``, ``_fault`` and ``_new_episode``. A tick runs under the fleet lock;
the loop thread waits for the workers outside it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from policy.controller import WATCHDOG, Mode, RobotStep, ends_episode
from server.assistance import AssistanceQueue
from server.recording import Recorder
from server.robot import Robot, TimelinePoint
from server.settings import Settings
from server.workers import Priority, WorkerFactory, WorkerFault, wait_any
from sim.frame import RobotFrame
from storage import keys

if TYPE_CHECKING:
    from server.policy_swap import PolicySwap

log = logging.getLogger("hitl.fleet")

RESTART_BACKOFF = (1.0, 2.0, 5.0, 10.0, 30.0)
# free-running (control_hz = 0): a tick waits (up to 50 ms) for this share of the busy workers to answer,
# or for a teleoperated robot (its operator's command waits for it). Stepping each robot as soon as it
# answered made ticks of ~5 of 16 robots, and DDIM's ten network calls per tick cost nearly as much for 5
# robots as for 16.
FREE_RUN_BATCH = 0.5


class ControlLoop:
    """The control tick, the loop thread that runs it, and the workers' and episodes' transitions."""

    settings: Settings
    queue: AssistanceQueue
    recorder: Recorder
    robots: dict[int, Robot]
    policies: PolicySwap
    lock: threading.RLock
    _stop: threading.Event
    worker_factory: WorkerFactory
    ticks: int
    env_steps: int
    tick_periods: deque
    loop_cpu_seconds: float
    operator_busy: dict[str, float]
    inference_holds: int  # robot-steps held since the inference back end last answered (0: it answers)

    # -- workers and episodes -------------------------------------------------------------------------------
    def _spawn(self, robot: Robot) -> None:
        robot.worker = self.worker_factory(robot.id, robot.task)
        robot.worker.prioritize(Priority.BACKGROUND)
        self._new_episode(robot)

    def _new_episode(self, robot: Robot) -> None:
        """The next episode, on the policy version assigned to the robot's lineage (hot swap)."""
        self.policies.move_to_assigned(robot)
        robot.seed += 1
        robot.slot.controller.reset(robot.id, robot.seed)
        robot.steps = robot.assisted_steps = robot.events = 0
        robot.timeline.clear()  # a plot of this episode's steps
        robot.teleop_left = None
        robot.fresh = False  # the last frame stays on view until the reset's arrives
        robot.commands.clear()
        robot.mode = "autonomous" if robot.mode != "paused" else "paused"
        if robot.mode == "paused":
            robot.paused_from = "autonomous"
        robot.episode_id = self.recorder.open_episode(robot)
        try:
            robot.worker.request_reset(robot.seed)
        except WorkerFault as exc:
            self._fault(robot, str(exc))

    def _end_episode(self, robot: Robot, frame: RobotFrame) -> None:
        """The episode ended on its own: success, or the horizon (never under an operator's hands)."""
        outcome = "success" if frame.success else "timeout"
        self.recorder.close_episode_file(robot, frame.success, frame.t, outcome)
        self._end_takeover(robot, "episode-ended")  # a takeover that reached success (a timeout waits for hand-back)
        robot.mode = "done" if robot.mode != "paused" else "paused"
        robot.episodes_done += 1
        robot.successes += int(frame.success)
        self.recorder.finish_episode(robot, outcome, frame.clock)
        self._new_episode(robot)

    def _interrupt(self, robot: Robot, outcome: str, ended_by: str) -> None:
        """Ends the episode early (fault, reset, shutdown): files and rows closed, request dropped.
        ended_by: why, for a takeover in progress (``db.SEGMENT_ENDS``)."""
        self._end_takeover(robot, ended_by)
        self.recorder.close_episode_file(robot, None, robot.steps, outcome)
        self.recorder.finish_episode(robot, outcome)
        robot.commands.clear()

    def _fault(self, robot: Robot, why: str) -> None:
        log.warning("robot %d faulted: %s", robot.id, why.splitlines()[-1] if why else why)
        self._interrupt(robot, "faulted", "worker-fault")
        robot.slot.controller.remove(robot.id)
        robot.mode, robot.fault, robot.fresh = "faulted", why, False
        if robot.worker is not None:
            robot.worker.kill()
        robot.worker = None
        robot.restart_at = time.monotonic() + RESTART_BACKOFF[min(robot.restarts, len(RESTART_BACKOFF) - 1)]
        robot.restarts += 1

    # -- the control loop --------------------------------------------------------------------------------
    def _loop(self) -> None:
        period = 1.0 / self.settings.control_hz if self.settings.control_hz > 0 else 0.0
        last = time.monotonic()
        try:
            while not self._stop.is_set():
                start = time.monotonic()
                if not period:  # free-running: block until enough workers answer (a batch), never spin
                    workers = [r.worker for r in self.robots.values() if r.worker is not None]
                    teleop = [r.worker for r in self.robots.values() if r.worker is not None and r.mode == "teleop"]
                    wait_any(workers, 0.05, math.ceil(FREE_RUN_BATCH * sum(w.busy for w in workers)), teleop)
                cpu = time.thread_time()
                try:
                    with self.lock:
                        worked = self.tick()
                except Exception:  # a bug in one tick must not stop the fleet
                    log.exception("control tick failed")
                    worked = False
                self.loop_cpu_seconds += time.thread_time() - cpu
                now = time.monotonic()
                if worked:
                    self.tick_periods.append(now - last)
                    last = now
                if period:
                    self._stop.wait(max(0.0, period - (now - start)))
                elif not worked:  # nothing to step (all paused or restarting): do not spin
                    self._stop.wait(0.01)
        finally:
            log.info("control loop stopped after %d ticks", self.ticks)

    def _collect(self, robot: Robot) -> None:
        """Takes the worker's answer if there is one (faults and restarts happen here)."""
        if robot.mode == "faulted":
            if robot.restart_at is not None and time.monotonic() >= robot.restart_at:
                robot.fault, robot.restart_at, robot.mode = None, None, "autonomous"
                self._spawn(robot)
            return
        if robot.worker is None:
            return
        try:
            frame = robot.worker.poll()
        except WorkerFault as exc:
            self._fault(robot, str(exc))
            return
        if frame is None:
            return
        robot.frame = frame
        self.recorder.frame_arrived(robot, frame)
        controller = robot.slot.controller
        mode = controller.mode(robot.id) if robot.id in controller else Mode.AUTONOMOUS
        if frame.t > 0 and ends_episode(frame, mode):
            self._end_episode(robot, frame)
        else:
            robot.fresh = True

    def tick(self) -> bool:
        """One control tick; returns whether any robot was stepped (only those ticks are counted)."""
        for req in self.queue.expire():  # lease ran out: the robot holds, the request is queued again
            if req.expired_holder and req.claimed_at is not None:
                self._add_busy(req.expired_holder, time.monotonic() - req.claimed_at)
            robot = self.robots.get(req.robot_id)
            if robot is None:
                continue
            self.recorder.close_segment(robot, "lease-expired")  # paused or not: the takeover is over
            robot.commands.clear()
            if robot.mode == "teleop" and robot.frame is not None:
                # (past the horizon, the next frame ends the episode: a timeout waited for this)
                robot.slot.controller.ask(robot.id, robot.frame.hold)
                robot.mode = "waiting"
        for r in self.robots.values():
            self._apply_handovers(r)  # claims and releases since the last tick (``server.handovers``)
            if r.segment is not None:  # nothing older than a second is only in memory
                r.segment.maybe_flush()
            if r.worker is not None:
                r.worker.prioritize(Priority.CONTROL if r.mode == "teleop" else Priority.BACKGROUND)
            self._collect(r)
        ready = [r for r in self.robots.values() if r.fresh and r.mode not in ("paused", "faulted")]
        if ready:
            self.ticks += 1
            by_slot: dict[int, list[Robot]] = {}
            for r in ready:
                by_slot.setdefault(r.slot.version, []).append(r)
            for robots in by_slot.values():
                self._step_slot(robots)
        for r in self.robots.values():
            r.publish()
        return bool(ready)

    def _step_slot(self, robots: list[Robot]) -> None:
        slot = robots[0].slot
        frames = {r.id: r.frame for r in robots}
        taken = {r.id: t for r in robots if r.mode == "teleop" and (t := r.commands.take()) is not None}
        commands = {rid: cmd for rid, (cmd, _, _) in taken.items()}
        # simulated robots that only hold while they wait for their operator (or for a command) are not
        # stepped when ``freeze_idle``: their scene waits with them, and their frame stays current
        idle = set()
        if self.settings.freeze_idle:
            modes = {r.id: slot.controller.mode(r.id) for r in robots if r.id in slot.controller}
            idle = {rid for rid, m in modes.items() if m == Mode.WAITING or (m == Mode.TELEOP and rid not in commands)}

        def send(rid: int, action: np.ndarray, source: str) -> None:
            if rid in idle:
                return
            self._send(self.robots[rid], action, source)
            if rid in taken and source == keys.SOURCE_OPERATOR:
                self.robots[rid].latencies.append(time.monotonic() - taken[rid][1])

        steps = slot.controller.step(frames, commands, send)
        for r in robots:
            r.fresh = r.id in idle  # a frozen robot's frame is still its current one
            if r.fault_pending is not None:  # its worker died while the step was being sent
                why, r.fault_pending = r.fault_pending, None
                self._fault(r, why)
                continue
            self._after_step(r, steps[r.id])

    def _after_step(self, robot: Robot, step: RobotStep) -> None:
        if step.unavailable is not None:  # the version's inference back end did not answer: the robot held
            if not self.inference_holds:
                log.warning("robot %d held: %s; retrying at every tick", robot.id, step.unavailable)
            self.inference_holds += 1
        elif self.inference_holds and robot.mode == "autonomous":
            log.info("inference answers again after %d held robot-steps", self.inference_holds)
            self.inference_holds = 0
        if step.uncertainty is not None:
            robot.u_history.append(step.uncertainty.U)
            robot.last_result = step.uncertainty
        if step.scores:
            robot.scores = dict(step.scores)
        self.recorder.step_decided(robot, step)
        if step.source == keys.SOURCE_OPERATOR:
            robot.assisted_steps += 1
            self.recorder.segment_step(robot, robot.frame, step)
        robot.mode = step.mode.value
        controller = robot.slot.controller
        robot.teleop_left = controller.teleop_left(robot.id) if robot.id in controller else None
        if robot.frame is not None:
            u = step.uncertainty.U if step.uncertainty is not None else None
            robot.record(TimelinePoint(robot.frame.clock, robot.mode, step.scores.get(controller.asking or ""), u))
        if step.asked:
            robot.events += 1
            asking = robot.slot.controller.asking
            if step.asked_by == WATCHDOG:
                f = robot.frame
                self.queue.open(robot.id, 1.0, 1.0, f"watchdog: {f.clock} of {f.horizon} steps without success")
            else:
                value, threshold = step.scores[asking], robot.slot.controller.signals[asking].threshold
                why = step.why or f"score {value:.3g} over {threshold:.3g}"
                self.queue.open(robot.id, value, threshold, f"{asking}: {why}")
        if step.returned:
            self._hand_back(robot)

    def _send(self, robot: Robot, action: np.ndarray, source: str) -> None:
        self.recorder.action_sent(robot, action, source)
        hold = source == keys.SOURCE_HOLD  # holding for an operator does not use up the episode
        try:
            robot.worker.request_step(action, hold)
        except WorkerFault as exc:  # faulted once the controller's step is over, not in the middle of it
            robot.fault_pending = str(exc)
            return
        robot.steps += 0 if hold else 1
        self.env_steps += 1
        now = time.monotonic()
        if robot.last_sent is not None:
            robot.action_periods.append(now - robot.last_sent)
        robot.last_sent = now

    def _add_busy(self, operator: str, seconds: float) -> None:
        self.operator_busy[operator] = self.operator_busy.get(operator, 0.0) + seconds

    def _hand_back(self, robot: Robot) -> None:
        """Control returns to the policy, which restarts from the next frame with a fresh history (an
        episode past its horizon then ends at that frame: its timeout waited for the hand-back)."""
        self._end_takeover(robot, "hand-back")
        if robot.id in robot.slot.controller:
            robot.slot.controller.release(robot.id)
        robot.commands.clear()
        if robot.mode == "paused":
            robot.paused_from = "autonomous"
        else:
            robot.mode = "autonomous"

    def _end_takeover(self, robot: Robot, ended_by: str) -> None:
        """Closes the takeover's segment and request, and books the operator's time."""
        self.recorder.close_segment(robot, ended_by)
        req = self.queue.close(robot.id)
        if req is not None and req.holder and req.claimed_at is not None:
            self._add_busy(req.holder, time.monotonic() - req.claimed_at)

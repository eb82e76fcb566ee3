"""The fleet's control loop: one tick over the robot workers, and the thread that runs it.

One control tick: collect every worker's latest frame (without waiting on any); for the robots that
are ready (a new frame, not paused), one ``Controller.step`` per policy slot: the policy and every
signal batched across that slot's robots, operator and hold actions sent before the batch is
computed. Workers whose robot is under teleop get the control loop's priority, the others a lower
one (``worker_niceness``): on a machine with fewer cores than robots, the batched policy step must
not queue behind the physics it feeds.

What a tick changes in a robot's life (an episode's end, a fault, a restart, a lease that ran out,
a hand-back) goes through ``server.fleet.lifecycle``; what it records, through the recorder. A tick
runs under the fleet lock; the loop thread waits for the workers outside it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque

import numpy as np

from policy.controller import RobotStep, ends_episode
from policy.hitl_state import Mode
from server.fleet.assistance import AskRecord, AssistanceQueue
from server.fleet.lifecycle import Lifecycle
from server.fleet.recording import Recorder
from server.fleet.robot import Robot, TimelinePoint
from server.settings import Settings
from server.workers import Priority, WorkerFault, wait_any
from storage import keys

log = logging.getLogger("hitl.fleet")

# free-running (control_hz = 0): a tick waits (up to 50 ms) for this share of the busy workers to answer,
# or for a teleoperated robot (its operator's command waits for it): a batched network call costs nearly
# as much for a few robots as for many, so stepping each robot as soon as it answered wastes it.
FREE_RUN_BATCH = 0.5
NOT_STEPPED = (Mode.PAUSED, Mode.FAULTED)


class ControlLoop:
    """The control tick and the loop thread that runs it, with the loop's own counters: ``ticks`` (that
    stepped a robot), ``env_steps`` (actions sent, all robots), ``tick_periods`` (seconds between ticks
    that stepped), ``loop_cpu_seconds`` and ``inference_holds`` (robot-steps held since the inference
    back end last answered; 0: it answers)."""

    def __init__(
        self,
        settings: Settings,
        robots: dict[int, Robot],
        lock: threading.RLock,
        queue: AssistanceQueue,
        recorder: Recorder,
        lifecycle: Lifecycle,
    ) -> None:
        self.settings = settings
        self.robots = robots
        self.lock = lock
        self.queue = queue
        self.recorder = recorder
        self.lifecycle = lifecycle
        self.ticks = 0
        self.env_steps = 0
        self.tick_periods: deque = deque(maxlen=2000)
        self.loop_cpu_seconds = 0.0
        self.inference_holds = 0
        self.running = False  # the loop thread runs: it applies the robots' inboxes (``server.fleet.inbox``)

    def run(self, stop: threading.Event) -> None:
        """The loop thread: ticks until ``stop`` is set, at ``control_hz`` or free-running."""
        period = 1.0 / self.settings.control_hz if self.settings.control_hz > 0 else 0.0
        last = time.monotonic()
        for r in self.robots.values():  # from now on only this thread changes a robot's control state
            r.control.bind_writer(threading.current_thread())
        self.running = True
        try:
            while not stop.is_set():
                start = time.monotonic()
                if not period:  # free-running: block until enough workers answer (a batch), never spin
                    workers = [r.worker for r in self.robots.values() if r.worker is not None]
                    teleop = [r.worker for r in self.robots.values() if r.worker is not None and r.mode == Mode.TELEOP]
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
                    stop.wait(max(0.0, period - (now - start)))
                elif not worked:  # nothing to step (all paused or restarting): do not spin
                    stop.wait(0.01)
        finally:
            self.running = False
            for r in self.robots.values():
                r.control.bind_writer(None)
            log.info("control loop stopped after %d ticks", self.ticks)

    def tick(self) -> bool:
        """One control tick (fleet lock held); returns whether any robot was stepped (only those ticks are
        counted)."""
        self.lifecycle.expire_leases(self.robots)
        for r in self.robots.values():
            self.lifecycle.apply_inbox(r)  # claims, releases and admin actions since the last tick
            self.recorder.flush_takeover(r)  # nothing older than a second is only in memory
            if r.worker is not None:
                r.worker.prioritize(Priority.CONTROL if r.mode == Mode.TELEOP else Priority.BACKGROUND)
            self._collect(r)
        ready = [r for r in self.robots.values() if r.fresh and r.mode not in NOT_STEPPED]
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

    def _collect(self, robot: Robot) -> None:
        """Takes the worker's answer if there is one (faults and restarts happen here)."""
        if robot.mode == Mode.FAULTED:
            self.lifecycle.restart_if_due(robot)
            return
        if robot.worker is None:
            return
        try:
            frame = robot.worker.poll()
        except WorkerFault as exc:
            self.lifecycle.fault(robot, str(exc))
            return
        if frame is None:
            return
        robot.frame = frame
        self.recorder.frame_arrived(robot, frame)
        if frame.t > 0 and ends_episode(frame, robot.control.stepped_mode):
            self.lifecycle.end_episode(robot, frame)
        else:
            robot.fresh = True

    def _step_slot(self, robots: list[Robot]) -> None:
        slot = robots[0].slot
        frames = {r.id: r.frame for r in robots}
        taken = {r.id: t for r in robots if r.mode == Mode.TELEOP and (t := r.inbox.take_command()) is not None}
        commands = {rid: cmd for rid, (cmd, _, _) in taken.items()}
        # simulated robots that only hold while they wait for their operator (or for a command) are not
        # stepped when ``freeze_idle``: their scene waits with them, and their frame stays current
        idle = set()
        if self.settings.workers.freeze_idle:
            idle = {r.id for r in robots if r.mode == Mode.WAITING or (r.mode == Mode.TELEOP and r.id not in commands)}

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
                self.lifecycle.fault(r, why)
                continue
            if r.id not in idle:
                self.recorder.step_taken(r, steps[r.id])
            self._after_step(r, steps[r.id])

    def _after_step(self, robot: Robot, step: RobotStep) -> None:
        if step.unavailable is not None:  # the version's inference back end did not answer: the robot held
            if not self.inference_holds:
                log.warning("robot %d held: %s; retrying at every tick", robot.id, step.unavailable)
            self.inference_holds += 1
        elif self.inference_holds and robot.mode == Mode.AUTONOMOUS:
            log.info("inference answers again after %d held robot-steps", self.inference_holds)
            self.inference_holds = 0
        controller = robot.slot.controller
        asking = controller.asking
        if step.uncertainty is not None:
            robot.u_history.append(step.uncertainty.U)
            robot.last_result = step.uncertainty
        if asking in step.scores:
            robot.score_history.append(step.scores[asking])
        if step.scores:
            robot.scores, robot.wants = dict(step.scores), dict(step.wants)
        if step.source == keys.SOURCE_OPERATOR:
            robot.assisted_steps += 1
            self.recorder.takeover_step(robot, robot.frame, step)
        if robot.frame is not None:
            u = step.uncertainty.U if step.uncertainty is not None else None
            robot.record(TimelinePoint(robot.frame.clock, robot.mode, step.scores.get(asking or ""), u))
        if step.asked:
            robot.events += 1
            # the robot shows the request the queue holds: the same signal, score, threshold and reason
            robot.ask = self.queue.ask(robot.id, AskRecord.of_step(step, controller, robot.frame)).ask
        if step.returned:
            self.lifecycle.hand_back(robot)

    def _send(self, robot: Robot, action: np.ndarray, source: str) -> None:
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

"""The fleet runtime: the control loop over the robot workers, and the service methods the API calls.

One control tick: collect every worker's latest frame (without waiting on any); for the robots that
are ready (a new frame, not paused), one ``Controller.step`` per policy slot: the policy and every
signal batched across that slot's robots, operator and hold actions sent before the batch is
computed. Workers whose robot is under teleop get the control loop's priority, the others a lower
one (``worker_niceness``): on a machine with fewer cores than robots, the batched policy step must
not queue behind the physics it feeds.

Modes: ``autonomous -> waiting -> teleop -> autonomous`` (the controller's), plus ``paused`` (not
stepped: the scene and the episode clock are frozen), ``done`` (then the next episode starts) and
``faulted`` (the worker died; it is restarted with backoff).

Policies swap without a restart. The registry (``server.registry``) says which version of each
lineage is active; ``sync_policies`` (called by a watcher thread every ``policy_poll_seconds``, and at
once by ``activate_policy``) loads a newly active version outside the fleet lock, and each robot of
that lineage moves to it at its next episode boundary; a robot in the middle of an episode finishes
it on the version it started with. So ``hitl policy promote`` or a fine-tuning job's promotion, from
another process, reaches the running fleet the same way as the admin API.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from policy.checkpoint import CheckpointError, read_info
from policy.controller import WATCHDOG, Mode, RobotStep, ends_episode
from server import registry
from server.assistance import AssistanceQueue
from server.commands import CommandMailbox
from server.db import PolicyVersion
from server.errors import ServiceError
from server.recording import Recorder
from server.robot import MODES, Robot, RobotView, TimelinePoint
from server.settings import Settings
from server.slots import PolicySlot, load_slot
from server.workers import WORKERS, Priority, WorkerFactory, WorkerFault, wait_any
from sim.frame import RobotFrame
from sim.registry import make_task
from sim.spaces import TeleopCommand
from storage import keys

log = logging.getLogger("hitl.fleet")

RESTART_BACKOFF = (1.0, 2.0, 5.0, 10.0, 30.0)
# free-running (control_hz = 0): a tick waits (up to 50 ms) for this share of the busy workers to answer,
# or for a teleoperated robot (its operator's command waits for it). Stepping each robot as soon as it
# answered made ticks of ~5 of 16 robots, and DDIM's ten network calls per tick cost nearly as much for 5
# robots as for 16.
FREE_RUN_BATCH = 0.5


class Fleet:
    """workers: how robots are started (default: the settings' ``worker`` back end)."""

    def __init__(self, settings: Settings, sessions: sessionmaker, workers: WorkerFactory | None = None) -> None:
        self.settings = settings
        self.sessions = sessions
        self.queue = AssistanceQueue(settings.lease_seconds)
        self.recorder = Recorder(sessions, settings.data_dir, settings.record_episodes)
        self.robots: dict[int, Robot] = {}
        self.slots: dict[int, PolicySlot] = {}  # by policy version id
        self.assigned: dict[str, PolicySlot] = {}  # lineage -> the slot its robots move to at their next episode
        self._unloadable: dict[int, str] = {}  # active versions that failed to load, and why (not retried)
        self._lineages: tuple[float, tuple] | None = None  # (when read, lineage summaries)
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._watcher: threading.Thread | None = None
        self._swap_lock = threading.Lock()  # one policy load at a time (outside the fleet lock)
        self.ticks = 0
        self.env_steps = 0  # actions sent to workers, all robots, since start
        self.tick_periods: deque = deque(maxlen=2000)
        self.loop_cpu_seconds = 0.0  # CPU time of the control loop's ticks
        self.operator_busy: dict[str, float] = {}  # seconds in control, per operator
        self.operator_since: dict[str, float] = {}  # first claim, per operator
        self._make_worker = workers if workers is not None else WORKERS[settings.worker](settings)
        self._build()

    # -- set-up -------------------------------------------------------------------------------------------
    def _build(self) -> None:
        rid = 0
        for group in self.settings.robots:
            slot = self._serve(group.policy_dir, group.task)
            limits = make_task(group.task).action_space.limits
            for _ in range(group.count):
                self.robots[rid] = Robot(rid, group.task, slot, self.settings.seed + 1000 * rid, CommandMailbox(limits))
                rid += 1

    def _serve(self, path: Path, task: str) -> PolicySlot:
        """The configured policy of a robot group, registered, and its lineage's active version loaded: a
        version promoted since (a fine-tuned one) is served, not the configured folder; a lineage with
        no active version gets the configured folder as its active one."""
        key = str(Path(path).resolve())
        with self.sessions() as s:
            row = s.scalars(select(PolicyVersion).where(PolicyVersion.path == key)).one_or_none()
        if row is None:
            info = _policy_info(Path(key))
            row = registry.register(
                self.sessions, key, info.get("task", task), status="candidate", command=info.get("command")
            )
        try:
            active = registry.resolve(self.sessions, registry.PolicyRef(row.name))
        except ServiceError:  # no active version yet
            active = registry.promote(self.sessions, row.id, "configured in the service's settings")
        if active.id != row.id:
            log.info(
                "%s is configured, but %s is the active version of its lineage (%s): serving it; "
                "`hitl policy promote %s` serves the configured one",
                key,
                active.ref,
                active.status_reason,
                row.ref,
            )
        if active.id in self._unloadable:
            active = row
        if active.id not in self.slots:
            try:
                slot = load_slot(self.settings, Path(active.path), task, active.id, active.name)
            except ServiceError as exc:
                if active.id == row.id:
                    raise
                log.error(
                    "the active %s cannot be served (%s): serving the configured %s", active.ref, exc.message, row.ref
                )
                self._unloadable[active.id] = exc.message
                active = row
                slot = self.slots.get(row.id) or load_slot(self.settings, Path(row.path), task, row.id, row.name)
            self.slots[active.id] = slot
            self.assigned[active.name] = slot
            with self.sessions() as s:
                s.get(PolicyVersion, active.id).threshold = slot.threshold
                s.commit()
        return self.slots[active.id]

    # -- workers and episodes -------------------------------------------------------------------------------
    def _spawn(self, robot: Robot) -> None:
        robot.worker = self._make_worker(robot.id, robot.task)
        robot.worker.prioritize(Priority.BACKGROUND)
        self._new_episode(robot)

    def _new_episode(self, robot: Robot) -> None:
        """The next episode, on the policy version assigned to the robot's lineage (hot swap)."""
        target = self.assigned.get(robot.slot.lineage)
        if target is not None and target is not robot.slot:
            old = robot.slot
            old.controller.remove(robot.id)
            robot.slot = target
            in_use = [r.slot for r in self.robots.values()] + list(self.assigned.values())
            if all(slot is not old for slot in in_use):
                self.slots.pop(old.version, None)  # no robot left on it: its weights and trace are freed
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
        while not self._stop.wait(self.settings.policy_poll_seconds):
            try:
                self.sync_policies()
            except Exception:  # noqa: BLE001 - a database hiccup: the next poll tries again
                log.exception("policy registry poll failed")

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
        if step.uncertainty is not None:
            robot.u_history.append(step.uncertainty.U)
            robot.last_result = step.uncertainty
        if step.scores:
            robot.scores = dict(step.scores)
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
                self.queue.open(robot.id, value, threshold, f"{asking} score {value:.3g} over {threshold:.3g}")
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

    # -- policy versions ----------------------------------------------------------------------------------
    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int:
        """Adds a policy folder as a ``candidate`` version (idempotent by path); returns its id."""
        key = str(Path(path).resolve())
        info = _policy_info(Path(key))
        task = task or info.get("task")
        if task is None:
            raise ServiceError(422, f"{key}/config.json names no task: give one")
        obs_dim = info.get("policy", {}).get("obs_dim")
        spec = _task_spec(task)
        if obs_dim != spec.obs_spec.dim:
            raise ServiceError(
                422, f"policy {key} expects {obs_dim}-dim observations, {task} gives {spec.obs_spec.dim}"
            )
        return registry.register(self.sessions, key, task, parent=parent, command=info.get("command")).id

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]:
        """The registry's lineages with their active version and last fine-tuning job (the console's
        view), read from the database at most every ``max_age`` seconds."""
        now = time.monotonic()
        if self._lineages is None or now - self._lineages[0] > max_age:
            try:
                self._lineages = (now, tuple(registry.lineage_summaries(self.sessions)))
            except Exception:  # noqa: BLE001 - a database hiccup: the last view, tried again later
                log.warning("reading the policy registry failed", exc_info=True)
                self._lineages = (now, self._lineages[1] if self._lineages else ())
        return self._lineages[1]

    def served_lineages(self) -> set[str]:
        with self.lock:
            return {r.slot.lineage for r in self.robots.values()} | set(self.assigned)

    def sync_policies(self) -> list[int]:
        """Loads the registry's active version of every lineage the fleet serves, if it is not the one
        assigned yet; returns the versions newly assigned. A version that cannot be loaded is logged
        once and the fleet keeps its current one."""
        changed = []
        with self._swap_lock:
            active = registry.active_versions(self.sessions)
            for lineage in sorted(self.served_lineages()):
                row = active.get(lineage)
                current = self.assigned.get(lineage)
                if row is None or (current is not None and current.version == row.id) or row.id in self._unloadable:
                    continue
                try:
                    slot = self._load(row)
                except ServiceError as exc:
                    self._unloadable[row.id] = exc.message
                    log.error(
                        "policy %s is active but cannot be served, keeping the current one: %s", row.ref, exc.message
                    )
                    continue
                with self.lock:
                    self.slots[row.id] = slot
                    self.assigned[lineage] = slot
                changed.append(row.id)
                log.info(
                    "policy %s (%s) now serves lineage %s from each robot's next episode", row.ref, row.path, lineage
                )
        return changed

    def _load(self, row: PolicyVersion) -> PolicySlot:
        """The slot of a version (slow: no fleet lock), its threshold recorded; ServiceError 422 when it
        cannot drive every robot of its lineage (another observation size)."""
        with self.lock:
            tasks = {r.task for r in self.robots.values() if r.slot.lineage == row.name}
        wanted = (_policy_info(Path(row.path)).get("policy") or {}).get("obs_dim") if tasks else None
        for task in sorted(tasks):
            dim = _task_spec(task).obs_spec.dim
            if wanted != dim:
                raise ServiceError(
                    422, f"policy {row.ref} expects {wanted}-dim observations, its lineage's {task} robots give {dim}"
                )
        slot = self.slots.get(row.id) or load_slot(self.settings, Path(row.path), row.task, row.id, row.name)
        with self.sessions() as s:
            s.get(PolicyVersion, row.id).threshold = slot.threshold
            s.commit()
        return slot

    def activate_policy(self, version: int, reason: str | None = None) -> None:
        """Promotes ``version`` in the registry and, when the fleet serves its lineage, loads it first (a
        version that cannot be served is refused with 422 and the registry is left as it was); each
        robot of the lineage moves to it at its next episode boundary."""
        row = registry.by_id(self.sessions, version)
        if row.name in self.served_lineages():
            with self._swap_lock:
                slot = self._load(row)
                with self.lock:
                    self.slots[row.id] = slot
            self._unloadable.pop(row.id, None)
        registry.promote(self.sessions, version, reason)
        self.sync_policies()

    # -- metrics --------------------------------------------------------------------------------------
    def metrics(self) -> dict:
        """Fleet metrics; the episode totals come from one aggregate query, outside the fleet lock."""
        totals = self.recorder.totals()
        n, success, assisted = totals["episodes"], totals["successes"], totals["assisted_steps"]
        waits = np.array(list(self.queue.waits))
        busy, since = dict(self.operator_busy), dict(self.operator_since)
        views = self.views()
        now = time.monotonic()
        return {
            "episodes": n,
            "success_rate": success / n if n else None,
            "assisted_steps_per_episode": assisted / n if n else None,
            "assistance_events_per_episode": totals["events"] / n if n else None,
            "queue_wait_p50_s": float(np.quantile(waits, 0.5)) if len(waits) else None,
            "queue_wait_p95_s": float(np.quantile(waits, 0.95)) if len(waits) else None,
            "operator_busy_s": busy,
            "operator_idle_s": {op: max(0.0, now - t0 - busy.get(op, 0.0)) for op, t0 in since.items()},
            "return_on_human_effort": success / assisted if assisted else None,
            "robots_by_mode": {m: sum(v.mode == m for v in views) for m in MODES},
            "ticks": self.ticks,
        }


def _policy_info(path: Path) -> dict:
    try:
        return read_info(path)
    except CheckpointError as exc:
        raise ServiceError(422, str(exc)) from exc


def _task_spec(task: str):
    try:
        return make_task(task)
    except KeyError as exc:
        raise ServiceError(422, str(exc)) from exc

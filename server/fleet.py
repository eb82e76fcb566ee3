"""The fleet runtime: robots in worker processes, the policy and its uncertainty batched across the
fleet in the server, robot modes, takeovers and their recording.

One control tick: collect every worker's latest frame (without waiting on any); for the robots
that are ready and moving (autonomous, or teleoperated with a command pending), one batched
action sample and one batched evaluation of every signal per policy; then each ready robot gets
its next action: the policy's, the operator's command, or a hold of the pose it had when it
stopped (no drift). Workers run at a lower CPU priority than the control loop
(``worker_niceness``): on a machine with fewer cores than robots, the batched policy step must
not queue behind the physics it feeds.

Modes: ``autonomous -> waiting -> teleop -> autonomous``, plus ``paused`` (not stepped: the scene
and the episode clock are frozen), ``done`` (then the next episode starts) and ``faulted`` (the
worker died; it is restarted with backoff).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from multiprocessing.connection import wait
from pathlib import Path

import numpy as np
import torch
from sqlalchemy.orm import sessionmaker

from policy.checkpoint import load_policy
from policy.signals import SignalError, load_signal
from policy.signals.base import Scores, SignalInput, TriggerState
from policy.uncertainty import UncertaintyResult
from server.assistance import AssistanceQueue, QueueError
from server.db import EpisodeRecord, PolicyVersion, SegmentRecord
from server.settings import Settings
from server.worker import worker_main
from sim.registry import make_task
from sim.spaces import TeleopCommand
from storage import keys
from storage.episodes import EpisodeWriter
from storage.segments import SegmentWriter

log = logging.getLogger("hitl.fleet")

MODES = ("autonomous", "waiting", "teleop", "paused", "done", "faulted")
U_HISTORY = 300
RESTART_BACKOFF = (1.0, 2.0, 5.0, 10.0, 30.0)


class FleetError(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass
class PolicySlot:
    id: int
    path: Path
    policy: object
    task: str
    threshold: float  # the denoising metric's (what the console draws U against)
    signals: dict  # name -> AssistanceSignal; always holds "denoising"
    active: str  # the signal that asks for help

    def score(self, batch: SignalInput) -> dict:
        return {name: signal.score(batch) for name, signal in self.signals.items()}

    def reset(self, robot_ids: list[int]) -> None:
        for signal in self.signals.values():
            signal.reset(robot_ids)


@dataclass(frozen=True)
class RobotView:
    """A robot as the API shows it, copied at the end of each tick and after each service call."""

    id: int
    task: str
    slot: PolicySlot
    mode: str
    episode_id: int | None
    steps: int
    u_history: tuple
    frame: dict | None
    last_result: UncertaintyResult | None
    episodes_done: int
    successes: int
    assisted_steps: int
    events: int
    restarts: int
    fault: str | None


@dataclass
class Robot:
    id: int
    task: str
    slot: PolicySlot
    action_space: object
    seed: int
    process: mp.Process | None = None
    conn: object | None = None
    mode: str = "autonomous"
    frame: dict | None = None
    awaiting: bool = False
    history: deque = field(default_factory=deque)
    hold_target: np.ndarray | None = None
    command: tuple[TeleopCommand, float] | None = None  # (command, monotonic receive time)
    applied: tuple | None = None  # (command, teleop target) sent this tick, awaiting its shadow scores
    teleop_left: int | None = None
    below: int = 0
    episode_id: int | None = None
    steps: int = 0
    assisted_steps: int = 0
    events: int = 0
    episodes_done: int = 0
    successes: int = 0
    u_history: deque = field(default_factory=lambda: deque(maxlen=U_HISTORY))
    last_result: UncertaintyResult | None = None
    segment: SegmentWriter | None = None
    segment_id: int | None = None
    restarts: int = 0
    restart_at: float | None = None
    fault: str | None = None
    paused_from: str | None = None
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))
    action_periods: deque = field(default_factory=lambda: deque(maxlen=1000))  # seconds between actions sent
    last_sent: float | None = None
    niceness: int | None = None  # the worker's current CPU priority (None: not set since spawn)
    recorder: EpisodeWriter | None = None  # whole-episode recording (settings.record_episodes)
    pending_step: tuple | None = None  # the step sent, written once its outcome arrives
    view: RobotView | None = None  # what readers see (``Fleet._publish``)


class Fleet:
    def __init__(self, settings: Settings, sessions: sessionmaker) -> None:
        self.settings = settings
        self.sessions = sessions
        self.queue = AssistanceQueue(settings.lease_seconds)
        self.robots: dict[int, Robot] = {}
        self.slots: dict[str, PolicySlot] = {}
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.ticks = 0
        self.env_steps = 0  # actions sent to workers, all robots, since start
        self.tick_periods: deque = deque(maxlen=2000)
        self._ctx = mp.get_context("spawn")
        self._priority_denied = False
        self.loop_cpu_seconds = 0.0  # CPU time of the control loop's ticks
        self.operator_busy: dict[str, float] = {}  # seconds in control, per operator
        self.operator_since: dict[str, float] = {}  # first claim, per operator
        self._build()

    # -- set-up -------------------------------------------------------------------------------------------
    def _slot(self, path: Path, task: str) -> PolicySlot:
        key = str(path.resolve())
        if key in self.slots:
            return self.slots[key]
        policy, info = load_policy(path)
        obs_dim = make_task(task).obs_spec.dim
        if policy.config.obs_dim != obs_dim:
            raise FleetError(
                500, f"policy {path} expects {policy.config.obs_dim}-dim observations, {task} gives {obs_dim}"
            )
        if self.settings.trace_policies:
            policy.freeze_for_inference()
        signals = {}
        for name in dict.fromkeys([self.settings.signal, "denoising", *self.settings.shadow_signals]):
            try:
                signals[name] = load_signal(policy, path, name)
            except (SignalError, ValueError) as exc:
                raise FleetError(500, f"policy {path}: signal {name!r} is not ready: {exc}") from exc
        with self.sessions() as s:
            row = s.query(PolicyVersion).filter_by(path=key).one_or_none()
            if row is None:
                row = PolicyVersion(
                    name=path.name, path=key, task=info.get("task", task), threshold=signals["denoising"].threshold
                )
                s.add(row)
                s.commit()
            pid = row.id
        slot = PolicySlot(pid, path, policy, task, float(signals["denoising"].threshold), signals, self.settings.signal)
        self.slots[key] = slot
        return slot

    def _build(self) -> None:
        rid = 0
        for group in self.settings.robots:
            slot = self._slot(group.policy_dir, group.task)
            for _ in range(group.count):
                task = make_task(group.task)  # its action space; the simulator lives in the worker
                self.robots[rid] = Robot(rid, group.task, slot, task.action_space, self.settings.seed + 1000 * rid)
                rid += 1

    # -- workers -------------------------------------------------------------------------------------------
    def _spawn(self, robot: Robot) -> None:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=worker_main, args=(child, robot.task), daemon=True, name=f"robot-{robot.id}")
        proc.start()
        child.close()
        robot.process, robot.conn = proc, parent
        robot.niceness, robot.last_sent = None, None
        self._prioritize(robot)
        self._new_episode(robot)

    def _new_episode(self, robot: Robot) -> None:
        robot.slot.reset([robot.id])
        robot.seed += 1
        robot.steps = robot.assisted_steps = robot.events = 0
        robot.history.clear()
        robot.hold_target = None
        robot.mode = "autonomous" if robot.mode != "paused" else "paused"
        with self.sessions() as s:
            row = EpisodeRecord(robot_id=robot.id, task=robot.task, seed=robot.seed, policy_id=robot.slot.id)
            s.add(row)
            s.commit()
            robot.episode_id = row.id
        robot.conn.send(("reset", robot.seed))
        robot.awaiting = True

    def _fault(self, robot: Robot, why: str) -> None:
        log.warning("robot %d faulted: %s", robot.id, why.splitlines()[-1] if why else why)
        self._close_segment(robot, "closed")
        self._close_recorder(robot, None, robot.steps, "faulted")
        self._finish_episode_row(robot, "faulted")
        self.queue.close(robot.id)
        robot.mode, robot.fault, robot.awaiting, robot.applied = "faulted", why, False, None
        if robot.process is not None and robot.process.is_alive():
            robot.process.kill()
        robot.process = robot.conn = None
        delay = RESTART_BACKOFF[min(robot.restarts, len(RESTART_BACKOFF) - 1)]
        robot.restart_at = time.monotonic() + delay
        robot.restarts += 1

    def start(self) -> None:
        # the physics workers keep the cores busy: intra-op threads in the server only contend with them
        torch.set_num_threads(self.settings.torch_threads)
        for robot in self.robots.values():
            self._spawn(robot)
        self._thread = threading.Thread(target=self._loop, name="fleet-control", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Finishes the current tick, closes open segments, stops the workers."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        with self.lock:
            for robot in self.robots.values():
                self._close_segment(robot, "closed")
                self._close_recorder(robot, None, robot.steps, "service stopped")
                self._finish_episode_row(robot, "stopped")
                if robot.conn is not None:
                    with contextlib.suppress(OSError, BrokenPipeError):
                        robot.conn.send(("close", None))
            for robot in self.robots.values():
                if robot.process is not None:
                    robot.process.join(timeout=5)
                    if robot.process.is_alive():
                        robot.process.kill()

    # -- the control loop --------------------------------------------------------------------------------
    def _loop(self) -> None:
        period = 1.0 / self.settings.control_hz if self.settings.control_hz > 0 else 0.0
        last = time.monotonic()
        try:
            while not self._stop.is_set():
                start = time.monotonic()
                if not period:  # free-running: block until some worker answers, never spin
                    with self.lock:
                        pending = [r.conn for r in self.robots.values() if r.awaiting and r.conn is not None]
                    if pending:
                        wait(pending, timeout=0.05)
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

    def _collect(self, robot: Robot) -> bool:
        """Takes the worker's answer if there is one; returns True when the robot is ready."""
        if robot.mode == "faulted":
            if robot.restart_at is not None and time.monotonic() >= robot.restart_at:
                robot.fault, robot.restart_at, robot.mode = None, None, "autonomous"
                self._spawn(robot)
            return False
        if robot.process is None or not robot.process.is_alive():
            self._fault(
                robot, f"worker process exited (code {None if robot.process is None else robot.process.exitcode})"
            )
            return False
        if robot.awaiting:
            try:
                if not robot.conn.poll():
                    return False
                status, payload = robot.conn.recv()
            except (EOFError, OSError) as exc:
                self._fault(robot, f"worker pipe broke: {exc}")
                return False
            robot.awaiting = False
            if status != "ok":
                self._fault(robot, str(payload))
                return False
            robot.frame = payload
            self._record(robot, payload)
            obs = torch.as_tensor(payload["obs"])
            if not robot.history:
                robot.history.extend([obs] * robot.slot.policy.config.obs_horizon)
            else:
                robot.history.append(obs)
            while len(robot.history) > robot.slot.policy.config.obs_horizon:
                robot.history.popleft()
            if payload["done"] and payload["t"] > 0:
                self._end_episode(robot)
                return False
        return robot.frame is not None

    def tick(self) -> bool:
        """One control tick; returns whether any robot was ready (only those ticks are counted)."""
        for req in self.queue.expire():  # lease ran out: the robot holds, the request is queued again
            if req.expired_holder and req.claimed_at is not None:
                busy = self.operator_busy.get(req.expired_holder, 0.0)
                self.operator_busy[req.expired_holder] = busy + time.monotonic() - req.claimed_at
            robot = self.robots.get(req.robot_id)
            if robot is not None and robot.mode == "teleop":
                robot.mode, robot.command = "waiting", None
                robot.hold_target = robot.frame["hold"].copy()
        for r in self.robots.values():  # nothing older than a second is only in memory
            if r.segment is not None:
                r.segment.maybe_flush()
            self._prioritize(r)
        ready = [r for r in self.robots.values() if self._collect(r) and r.mode != "paused"]
        if not ready:
            for r in self.robots.values():  # faults, restarts and pauses still show
                self._publish(r)
            return False
        self.ticks += 1
        for r in ready:  # the operator's command goes out first: it does not wait for the fleet's batch
            if r.mode == "teleop" and r.command is not None:
                self._send_command(r)
        moving = (r for r in ready if r.mode == "autonomous" or (r.mode == "teleop" and r.applied is not None))
        for robots in _by_slot(moving).values():
            self._step_slot(robots)
        for r in ready:
            if not r.awaiting and r.mode in ("waiting", "teleop"):  # hold the pose; paused robots are not stepped
                self._send(r, r.hold_target if r.hold_target is not None else r.frame["hold"])
        for r in self.robots.values():
            self._publish(r)
        return True

    def _prioritize(self, robot: Robot) -> None:
        """A teleoperated robot's worker runs at the control loop's priority, the others below it:
        the operator's robot does not queue behind the fleet's physics. Raising a priority again
        needs CAP_SYS_NICE; without it every worker stays at ``worker_niceness``."""
        want = 0 if robot.mode == "teleop" else self.settings.worker_niceness
        if robot.niceness == want or robot.process is None or robot.process.pid is None:
            return
        try:
            os.setpriority(os.PRIO_PROCESS, robot.process.pid, want)
        except PermissionError:
            if not self._priority_denied:
                log.info("cannot raise worker priority for teleoperated robots (needs CAP_SYS_NICE)")
            self._priority_denied = True
            want = self.settings.worker_niceness
        except ProcessLookupError:  # exited: the next collect faults it
            return
        robot.niceness = want

    def _batch(self, robots: list[Robot]) -> tuple[torch.Tensor, torch.Tensor]:
        obs = torch.stack([torch.stack(list(r.history)) for r in robots])
        current = torch.as_tensor(np.stack([r.frame["hold"] for r in robots]), dtype=torch.float32)
        return obs, current

    def _step_slot(self, robots: list[Robot]) -> None:
        """One batched action sample and one batched scoring of every signal for the robots of one
        policy: the autonomous ones act on it (or ask), the teleoperated ones apply their pending
        command and are scored in shadow (for the segment, the console and auto-return)."""
        slot = robots[0].slot
        obs, current = self._batch(robots)
        ids = np.array([r.id for r in robots])
        teleop = np.array([r.mode == "teleop" for r in robots])
        operator = None
        if teleop.any():
            operator = torch.full((len(robots), 10), float("nan"))
            for j in np.flatnonzero(teleop):
                operator[j] = torch.as_tensor(robots[j].applied[1].action, dtype=torch.float32)
        with torch.no_grad():
            chunks = slot.policy.predict_action_chunk(obs)
            scores = slot.score(SignalInput(obs, current, ids, action=chunks, operator_action=operator))
        auto = np.flatnonzero(~teleop)
        active = slot.signals[slot.active]
        if len(auto):  # the asking signal's trigger rule sees only the robots the policy drives
            wants = active.wants_help(_take(scores[slot.active], auto), TriggerState.autonomous(ids[auto]))
            asks = dict(zip(auto.tolist(), wants, strict=True))
        for j, r in enumerate(robots):
            if teleop[j]:
                self._after_command(r, scores, j)
                continue
            self._remember(r, scores["denoising"], j)
            if asks[j] and self.settings.assistance:
                value, threshold = float(scores[slot.active].value[j]), active.threshold
                r.mode, r.hold_target = "waiting", r.frame["hold"].copy()
                r.events += 1
                self.queue.open(r.id, value, threshold, f"{slot.active} score {value:.3g} over {threshold:.3g}")
                self._send(r, r.hold_target)
            else:
                self._send(r, chunks[j, 0].numpy().astype(np.float64), keys.SOURCE_POLICY)

    def _remember(self, robot: Robot, scores, j: int) -> None:
        res = scores.detail.robot(j)
        robot.u_history.append(res.U)
        robot.last_result = res

    def _send_command(self, robot: Robot) -> None:
        """Sends the robot's pending operator command (the tick's shadow scoring follows)."""
        (cmd, received), robot.command = robot.command, None  # a command arriving meanwhile waits for the next tick
        target = robot.action_space.apply_teleop(cmd, robot.frame["pos"], robot.frame["rot"])
        robot.hold_target = target.action.copy()
        robot.applied = (cmd, target)
        self._send(robot, target.action, keys.SOURCE_OPERATOR)
        robot.latencies.append(time.monotonic() - received)

    def _after_command(self, robot: Robot, scores: dict, j: int) -> None:
        """The command's shadow scores: segment step, console field, budget and auto-return."""
        slot = robot.slot
        (cmd, target), robot.applied = robot.applied, None
        action = target.action
        self._remember(robot, scores["denoising"], j)
        u = float(scores["denoising"].value[j])
        if robot.segment is not None:
            label = slot.policy.normalize_action(torch.as_tensor(action, dtype=torch.float32)).numpy()
            robot.segment.write_step(
                robot.frame["obs"],
                {
                    "delta_pos": list(cmd.delta_pos),
                    "delta_rot": list(cmd.delta_rot),
                    "gripper": cmd.gripper,
                    "clamped": list(target.clamped),
                },
                action,
                label,
                robot.frame["pos"],
                robot.frame["quat"],
                u,
                shadow={name: float(sc.value[j]) for name, sc in scores.items() if name != "denoising"},
                field=_world_field(slot, robot.last_result),  # the field just remembered
            )
        robot.assisted_steps += 1
        robot.below = robot.below + 1 if u <= slot.threshold else 0
        if robot.teleop_left is not None:
            robot.teleop_left -= 1
        auto_k = self.settings.auto_return_steps
        if (robot.teleop_left is not None and robot.teleop_left <= 0) or (auto_k and robot.below >= auto_k):
            self._hand_back(robot)

    def _send(self, robot: Robot, action: np.ndarray, source: str = keys.SOURCE_HOLD) -> None:
        if robot.recorder is not None and robot.frame is not None:
            f = robot.frame
            robot.pending_step = (
                f["t"],
                f["obs"],
                np.asarray(action, np.float64),
                f["pos"],
                f["quat"],
                f["gripper"],
                source,
                f["bodies"],
            )
        try:
            robot.conn.send(("step", np.asarray(action, dtype=np.float64)))
            robot.awaiting = True
            robot.steps += 1
            self.env_steps += 1
            now = time.monotonic()
            if robot.last_sent is not None:
                robot.action_periods.append(now - robot.last_sent)
            robot.last_sent = now
        except (OSError, BrokenPipeError) as exc:
            self._fault(robot, f"worker pipe broke: {exc}")

    def _record(self, robot: Robot, frame: dict) -> None:
        """Whole-episode MCAP recording: the step sent last, with the success that followed it."""
        if not self.settings.record_episodes:
            return
        if robot.pending_step is not None and robot.recorder is not None:
            t, obs, action, pos, quat, gripper, source, bodies = robot.pending_step
            robot.recorder.write_step(t, obs, action, pos, quat, gripper, frame["success"], source, bodies)
        robot.pending_step = None
        if frame["t"] == 0 and not frame["done"] and robot.recorder is None:
            path = Path(self.settings.data_dir) / "episodes" / f"robot{robot.id:03d}_ep{robot.episode_id:06d}.mcap"
            meta = {"task": robot.task, "seed": robot.seed, "robot": robot.id, "policy": str(robot.slot.path)}
            robot.recorder = EpisodeWriter(path, meta, object_names=list(frame["bodies"]))
            with self.sessions() as s:
                row = s.get(EpisodeRecord, robot.episode_id)
                if row is not None:
                    row.path = str(path)
                    s.commit()

    def _close_recorder(self, robot: Robot, success: bool | None, steps: int, reason: str) -> None:
        rec, robot.recorder, robot.pending_step = robot.recorder, None, None
        if rec is None:
            return
        if success is None:
            rec.close()  # unfinished: readable with recover=True
        else:
            rec.finish(success, steps, reason)

    def _finish_episode_row(self, robot: Robot, outcome: str) -> None:
        """Ends the episode's row early (faulted, reset) so that no episode stays open forever."""
        with self.sessions() as s:
            row = s.get(EpisodeRecord, robot.episode_id) if robot.episode_id is not None else None
            if row is not None and row.outcome is None:
                row.outcome, row.steps, row.ended_at = outcome, robot.steps, datetime.now(UTC)
                row.assisted_steps, row.assistance_events = robot.assisted_steps, robot.events
                s.commit()

    def _end_episode(self, robot: Robot) -> None:
        frame = robot.frame
        outcome = "success" if frame["success"] else "timeout"
        self._close_recorder(robot, bool(frame["success"]), int(frame["t"]), outcome)
        self._close_segment(robot, "closed")
        self.queue.close(robot.id)
        robot.mode = "done" if robot.mode != "paused" else "paused"
        robot.episodes_done += 1
        robot.successes += int(frame["success"])
        with self.sessions() as s:
            row = s.get(EpisodeRecord, robot.episode_id)
            if row is not None:
                row.outcome, row.steps = outcome, int(frame["t"])
                row.assisted_steps, row.assistance_events = robot.assisted_steps, robot.events
                row.ended_at = datetime.now(UTC)
                s.commit()
        robot.frame = None
        self._new_episode(robot)

    # -- takeovers -----------------------------------------------------------------------------------------
    def _open_segment(self, robot: Robot, operator: str, reason: str) -> None:
        folder = Path(self.settings.data_dir) / "segments"
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%f")
        path = folder / f"robot{robot.id:03d}_ep{robot.episode_id}_{stamp}.mcap"
        meta = {
            "robot": robot.id,
            "episode": robot.episode_id,
            "policy_version": robot.slot.id,
            "policy": str(robot.slot.path),
            "operator": operator,
            "task": robot.task,
            "reason": reason,
            "seed": robot.seed,
        }
        robot.segment = SegmentWriter(path, meta)
        with self.sessions() as s:
            row = SegmentRecord(
                robot_id=robot.id,
                episode_id=robot.episode_id,
                task=robot.task,
                policy_id=robot.slot.id,
                operator=operator,
                reason=reason,
                status="open",
                path=str(path),
                meta=meta,
            )
            s.add(row)
            s.commit()
            robot.segment_id = row.id

    def _close_segment(self, robot: Robot, status: str) -> None:
        if robot.segment is None:
            return
        writer, robot.segment = robot.segment, None
        writer.close(status)
        with self.sessions() as s:
            row = s.get(SegmentRecord, robot.segment_id)
            if row is not None:
                row.status, row.steps, row.ended_at = status, writer.steps, datetime.now(UTC)
                s.commit()
        robot.segment_id = None

    def _hand_back(self, robot: Robot) -> None:
        """The policy restarts from the current pose with a fresh observation history."""
        self._close_segment(robot, "closed")
        req = self.queue.close(robot.id)
        if req is not None and req.holder and req.claimed_at is not None:
            self.operator_busy[req.holder] = self.operator_busy.get(req.holder, 0.0) + time.monotonic() - req.claimed_at
        robot.mode, robot.teleop_left, robot.command, robot.below = "autonomous", None, None, 0
        robot.hold_target = None
        robot.history.clear()
        if robot.frame is not None:
            obs = torch.as_tensor(robot.frame["obs"])
            robot.history.extend([obs] * robot.slot.policy.config.obs_horizon)

    # -- what readers see -------------------------------------------------------------------------------------
    def _publish(self, robot: Robot) -> None:
        """A consistent copy of what the API shows, so readers never wait for a tick in progress."""
        values = {f.name: getattr(robot, f.name) for f in fields(RobotView)}
        robot.view = RobotView(**values | {"u_history": tuple(robot.u_history)})

    def view(self, robot_id: int) -> RobotView:
        robot = self.robot(robot_id)
        if robot.view is None:
            with self.lock:
                self._publish(robot)
        return robot.view

    def views(self) -> list[RobotView]:
        return [self.view(i) for i in sorted(self.robots)]

    # -- service methods (the API calls these) ---------------------------------------------------------------
    def robot(self, robot_id: int) -> Robot:
        robot = self.robots.get(robot_id)
        if robot is None:
            raise FleetError(404, f"no robot {robot_id}")
        return robot

    def claim(self, robot_id: int, operator: str):
        with self.lock:
            robot = self.robot(robot_id)
            req = self.queue.claim(robot_id, operator)
            self.operator_since.setdefault(operator, time.monotonic())
            if robot.mode == "waiting":
                robot.mode = "teleop"
                robot.teleop_left = self.settings.budget_steps if self.settings.trigger_mode == "budgeted" else None
                robot.command = None
                if robot.segment is None:
                    self._open_segment(robot, operator, req.reason)
            self._publish(robot)
            return req

    def heartbeat(self, robot_id: int, operator: str):
        with self.lock:
            self.robot(robot_id)
            return self.queue.heartbeat(robot_id, operator)

    def release(self, robot_id: int, operator: str) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            self.queue.check_holder(robot_id, operator)
            self._hand_back(robot)
            self._publish(robot)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> None:
        """Stores the command for the next tick. It does not wait for a tick in progress (no fleet lock):
        the command slot is one attribute, swapped atomically by the tick."""
        robot = self.robot(robot_id)
        self.queue.check_holder(robot_id, operator)
        if robot.mode != "teleop":
            raise QueueError(409, f"robot {robot_id} is {robot.mode}, not under teleop")
        robot.command = (command, time.monotonic())

    def pause(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode in ("faulted",):
                raise FleetError(409, f"robot {robot_id} is faulted")
            if robot.mode != "paused":
                robot.paused_from, robot.mode = robot.mode, "paused"
                if robot.frame is not None:
                    robot.hold_target = robot.frame["hold"].copy()
            self._publish(robot)

    def resume(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode != "paused":
                raise FleetError(409, f"robot {robot_id} is {robot.mode}, not paused")
            back = robot.paused_from if robot.paused_from in ("waiting", "teleop") else "autonomous"
            req = self.queue.get(robot_id)
            if back == "teleop" and (req is None or req.holder is None):  # the lease ran out while paused
                back = "waiting" if req is not None else "autonomous"
            robot.mode, robot.paused_from = back, None
            if back == "autonomous":
                robot.hold_target = None
            self._publish(robot)

    def reset(self, robot_id: int) -> None:
        with self.lock:
            robot = self.robot(robot_id)
            if robot.mode == "faulted":
                raise FleetError(409, f"robot {robot_id} is faulted; it restarts by itself")
            self._close_segment(robot, "closed")
            self._close_recorder(robot, None, robot.steps, "reset")
            self._finish_episode_row(robot, "reset")
            self.queue.close(robot.id)
            if robot.awaiting:  # the answer to the step in flight is dropped
                with contextlib.suppress(EOFError, OSError):
                    robot.conn.recv()
            robot.frame, robot.mode = None, "autonomous"
            self._new_episode(robot)
            self._publish(robot)

    def metrics(self) -> dict:
        with self.lock:
            robots = list(self.robots.values())
            waits = np.array(self.queue.waits) if self.queue.waits else np.zeros(0)
            with self.sessions() as s:
                rows = s.query(EpisodeRecord).filter(EpisodeRecord.outcome.in_(("success", "timeout"))).all()
            n = len(rows)
            success = sum(r.outcome == "success" for r in rows)
            assisted = sum(r.assisted_steps for r in rows)
            return {
                "episodes": n,
                "success_rate": success / n if n else None,
                "assisted_steps_per_episode": assisted / n if n else None,
                "assistance_events_per_episode": sum(r.assistance_events for r in rows) / n if n else None,
                "queue_wait_p50_s": float(np.quantile(waits, 0.5)) if len(waits) else None,
                "queue_wait_p95_s": float(np.quantile(waits, 0.95)) if len(waits) else None,
                "operator_busy_s": dict(self.operator_busy),
                "operator_idle_s": {
                    op: max(0.0, time.monotonic() - since - self.operator_busy.get(op, 0.0))
                    for op, since in self.operator_since.items()
                },
                "return_on_human_effort": success / assisted if assisted else None,
                "robots_by_mode": {m: sum(r.mode == m for r in robots) for m in MODES},
                "ticks": self.ticks,
            }


def _take(scores: Scores, rows: np.ndarray) -> Scores:
    """The scores of some rows of a batch (values and parts; the detail stays with the batch)."""
    return Scores(np.asarray(scores.value)[rows], {k: np.asarray(v)[rows] for k, v in scores.parts.items()})


def _by_slot(robots) -> dict[int, list[Robot]]:
    out: dict[int, list[Robot]] = {}
    for r in robots:
        out.setdefault(r.slot.id, []).append(r)
    return out


def _world_field(slot: PolicySlot, result: UncertaintyResult) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The probe samples in metres (world frame) and the denoising directions (-ε, rescaled per axis
    from the normalized action space), for the segment's arrows; the longest arrow is 2 cm."""
    norm = slot.policy.action_normalizer
    low, span = norm.low[:3].numpy().astype(np.float64), norm.span[:3].numpy().astype(np.float64)
    samples = result.samples * span + low
    vectors = -result.vectors * span
    longest = float(np.linalg.norm(vectors, axis=1).max()) if len(vectors) else 0.0
    return samples, vectors, result.labels, 0.02 / longest if longest > 0 else 0.0

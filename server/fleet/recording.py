"""What the fleet writes: episode rows, takeovers (MCAP + row: the stored name is "segment") and, when
asked, whole episodes as MCAP files; and ``recover``, which puts right what a crash left open.

The recorder owns its per-robot state (``_Recording``: the open episode file, the step waiting for its
outcome, the open takeover): the fleet tells it what happened to a robot, and it keeps what it needs.
A step's record is made once, when the controller has decided it (``step_taken``), and written when
the robot's next frame brings its outcome (``frame_arrived``: success).

File paths are stored relative to the service's ``data_dir`` (``storage.paths.store_relative``) and
opened against it (``storage.paths.in_store``), so the data folder can move and recovery does not
depend on the working directory.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch
from sqlalchemy import case, func, select
from sqlalchemy.orm import sessionmaker

from policy.controller import RobotStep
from server.db import FINISHED, EpisodeRecord, SegmentRecord
from server.fleet.assistance import AskRecord
from server.fleet.robot import Robot
from sim.frame import RobotFrame
from sim.registry import make_task
from sim.spaces import ACTION_LABELS
from storage import keys
from storage.episodes import EpisodeReadError, EpisodeWriter, recover_episode
from storage.paths import in_store, store_relative
from storage.segments import SegmentReadError, SegmentWriter, recover_segment

log = logging.getLogger("hitl.recording")


def request_meta(ask: AskRecord) -> dict:
    """A takeover file's ``request`` metadata: the request it answers (``storage.segments.Segment.request``);
    a score that is not finite is null there (JSON has no infinity; the row's column keeps it)."""

    def finite(x: float | None) -> float | None:
        return float(x) if x is not None and math.isfinite(x) else None

    return {
        "signal": ask.signal,
        "score": finite(ask.score),
        "threshold": finite(ask.threshold),
        "reason": ask.reason,
        "asked_at_step": ask.asked_at_step,
        "paper_u": finite(ask.paper_u),
    }


@dataclass(frozen=True)
class EpisodeTotals:
    """The episodes that ended on their own (``db.FINISHED``), summed."""

    episodes: int = 0
    successes: int = 0
    assisted_steps: int = 0
    events: int = 0


@dataclass(frozen=True)
class PendingStep:
    """A step sent and not yet written: the frame it was decided on, what was sent, and its record's
    extras (``keys.STEP_EXTRAS``); its outcome (success) comes with the next frame."""

    frame: RobotFrame
    action: np.ndarray
    source: str
    extras: dict


@dataclass
class _Recording:
    """One robot's open files: its whole-episode file and the step waiting for its outcome
    (``record_episodes``), and its takeover in progress with its row's id."""

    episode: EpisodeWriter | None = None
    pending: PendingStep | None = None
    takeover: SegmentWriter | None = None
    takeover_id: int | None = None


class Recorder:
    """segment_flush_seconds, segment_fsync: how durable a takeover's steps are (``SegmentWriter``; the
    settings of the same names, docs/service.md)."""

    def __init__(
        self,
        sessions: sessionmaker,
        data_dir: Path,
        record_episodes: bool,
        segment_flush_seconds: float = 0.0,
        segment_fsync: bool = False,
    ) -> None:
        self.sessions = sessions
        self.data_dir = Path(data_dir).resolve()
        self.record_episodes = record_episodes
        self.segment_flush_seconds, self.segment_fsync = segment_flush_seconds, segment_fsync
        self._robots: dict[int, _Recording] = {}
        self._totals: EpisodeTotals | None = None  # ``totals()`` until the next episode row ends
        self._ended = 0  # episode rows ended by this recorder: a ``totals()`` computed across one is not kept

    def _of(self, robot: Robot) -> _Recording:
        return self._robots.setdefault(robot.id, _Recording())

    # -- episode rows ---------------------------------------------------------------------------------
    def open_episode(self, robot: Robot) -> int:
        with self.sessions() as s:
            row = EpisodeRecord(robot_id=robot.id, task=robot.task, seed=robot.seed, policy_id=robot.slot.version)
            s.add(row)
            s.commit()
            return row.id

    def finish_episode(self, robot: Robot, outcome: str, steps: int | None = None) -> None:
        """Ends the episode's row (once): outcome, steps, assistance and end time."""
        with self.sessions() as s:
            row = s.get(EpisodeRecord, robot.episode_id) if robot.episode_id is not None else None
            if row is not None and row.outcome is None:
                row.outcome, row.steps, row.ended_at = (
                    outcome,
                    robot.steps if steps is None else steps,
                    datetime.now(UTC),
                )
                row.assisted_steps, row.assistance_events = robot.assisted_steps, robot.events
                s.commit()
                self._ended += 1
                self._totals = None

    def totals(self) -> EpisodeTotals:
        """Aggregates over the episodes that ended on their own (one query, no rows loaded). The fleet is
        the only writer of its episode rows, so the answer is kept until its next episode ends: a
        monitoring client polling the fleet's metrics costs no query between episodes."""
        if (kept := self._totals) is not None:
            return kept
        ended = self._ended
        with self.sessions() as s:
            n, success, assisted, events = s.execute(
                select(
                    func.count(EpisodeRecord.id),
                    func.coalesce(func.sum(case((EpisodeRecord.outcome == "success", 1), else_=0)), 0),
                    func.coalesce(func.sum(EpisodeRecord.assisted_steps), 0),
                    func.coalesce(func.sum(EpisodeRecord.assistance_events), 0),
                ).where(EpisodeRecord.outcome.in_(FINISHED))
            ).one()
        out = EpisodeTotals(int(n), int(success), int(assisted), int(events))
        if ended == self._ended:  # no episode ended while it was computed
            self._totals = out
        return out

    # -- whole episodes ---------------------------------------------------------------------------------
    def frame_arrived(self, robot: Robot, frame: RobotFrame) -> None:
        """Writes the step taken last with the success that followed it; opens the file at a reset."""
        if not self.record_episodes:
            return
        rec = self._of(robot)
        if (p := rec.pending) is not None and rec.episode is not None:
            f = p.frame
            cameras = [c["name"] for c in rec.episode.meta.get(keys.CAMERAS, [])]
            rec.episode.write_step(
                f.t,
                f.obs,
                p.action,
                f.pos,
                f.quat,
                f.gripper,
                frame.success,
                p.source,
                f.bodies,
                p.extras,
                images={c: f.images[c] for c in cameras},
            )
        rec.pending = None
        if frame.t == 0 and not frame.done and rec.episode is None:
            path = self.data_dir / "episodes" / f"robot{robot.id:03d}_ep{robot.episode_id:06d}.mcap"
            task = make_task(robot.task, images=robot.images)  # cheap: names and specs only
            meta = {
                "task": robot.task,
                "seed": robot.seed,
                "robot": robot.id,
                "episode": robot.episode_id,
                "policy": str(robot.slot.path),
                "policy_version": robot.slot.version,
                "signal": robot.slot.controller.asking,
                "obs_labels": task.obs_spec.labels(),
                "action_labels": list(ACTION_LABELS),
                "source": "fleet",
            }
            sees = [c for c in task.cameras if c.name in frame.images] if robot.images else []
            cameras = [c.to_json() for c in sees]  # what the policy saw, with every step
            rec.episode = EpisodeWriter(path, meta, object_names=list(frame.bodies), cameras=cameras)
            with self.sessions() as s:
                row = s.get(EpisodeRecord, robot.episode_id)
                if row is not None:
                    row.path = store_relative(self.data_dir, path)
                    s.commit()

    def step_taken(self, robot: Robot, step: RobotStep) -> None:
        """The step the robot was just sent, with what the controller decided about it: the asking
        signal's score and threshold, the paper's U, and on an operator step the command and the
        takeover it belongs to. Written when its outcome arrives (``frame_arrived``)."""
        rec = self._of(robot)
        if rec.episode is None or robot.frame is None:
            return
        controller = robot.slot.controller
        extras: dict = {keys.STEP_POLICY_VERSION: robot.slot.version}
        asking = controller.asking
        if asking is not None and asking in step.scores:
            extras[keys.STEP_SCORE] = float(step.scores[asking])
            extras[keys.STEP_THRESHOLD] = float(controller.signals[asking].threshold)
        if step.uncertainty is not None:
            extras[keys.STEP_PAPER_U] = float(step.uncertainty.U)
        if step.command is not None and step.source == keys.SOURCE_OPERATOR:
            extras[keys.STEP_COMMAND] = step.command.to_dict()
            if rec.takeover_id is not None:
                extras[keys.STEP_TAKEOVER] = rec.takeover_id
        rec.pending = PendingStep(robot.frame, np.asarray(step.action, np.float64), step.source, extras)

    def close_episode_file(self, robot: Robot, success: bool | None, steps: int, reason: str) -> None:
        rec = self._of(robot)
        writer, rec.episode, rec.pending = rec.episode, None, None
        if writer is None:
            return
        if success is None:
            writer.close()  # unfinished: readable with recover=True
        else:
            writer.finish(success, steps, reason)

    # -- takeovers (stored as segments) -----------------------------------------------------------------
    def takeover_operator(self, robot: Robot) -> str | None:
        """Who the robot's open takeover records as its operator (None: no takeover open)."""
        writer = self._of(robot).takeover
        return None if writer is None else writer.meta.get("operator")

    def flush_takeover(self, robot: Robot) -> None:
        """Nothing of the open takeover older than ``segment_flush_seconds`` stays only in memory."""
        if (writer := self._of(robot).takeover) is not None:
            writer.maybe_flush()

    def open_takeover(self, robot: Robot, operator: str, ask: AskRecord) -> None:
        """Opens the robot's takeover file and row. ``ask``: the request it answers, kept in the file's
        ``request`` metadata and the row's signal, score, threshold, reason and paper_u; the metadata's
        ``signal`` and ``threshold`` are the asking signal's, whose score each step records."""
        rec = self._of(robot)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%f")
        path = self.data_dir / "segments" / f"robot{robot.id:03d}_ep{robot.episode_id}_{stamp}.mcap"
        meta = {
            "robot": robot.id,
            "episode": robot.episode_id,
            "policy_version": robot.slot.version,
            "policy": str(robot.slot.path),
            "operator": operator,
            "task": robot.task,
            "reason": ask.reason,
            "seed": robot.seed,
            "signal": robot.slot.controller.asking,
            "threshold": robot.slot.asking_threshold,
            "request": request_meta(ask),
        }
        # the file names its observation's channels (what fine-tuning checks against the policy's); the row does not
        labels = {keys.OBS_LABELS: make_task(robot.task, images=robot.images).obs_spec.labels()}
        if robot.images:  # the frames the policy saw, with every step: what fine-tuning trains it on
            labels[keys.CAMERAS] = [c.to_json() for c in robot.slot.policy.config.cameras]
        rec.takeover = SegmentWriter(path, meta | labels, self.segment_flush_seconds, self.segment_fsync)
        with self.sessions() as s:
            row = SegmentRecord(
                robot_id=robot.id,
                episode_id=robot.episode_id,
                task=robot.task,
                policy_id=robot.slot.version,
                operator=operator,
                reason=ask.reason,
                signal=ask.signal,
                score=ask.score,
                threshold=ask.threshold,
                paper_u=ask.paper_u,
                status="open",
                path=store_relative(self.data_dir, path),
                meta=meta,
            )
            s.add(row)
            s.commit()
            rec.takeover_id = row.id

    def takeover_step(self, robot: Robot, frame: RobotFrame, step: RobotStep) -> None:
        """One operator step: the command, the absolute action and its normalized fine-tune label,
        every signal's score and the denoising field (world frame)."""
        writer = self._of(robot).takeover
        if writer is None or step.command is None or step.target is None:
            return
        policy = robot.slot.policy
        label = policy.normalize_action(torch.as_tensor(step.action, dtype=torch.float32)).numpy()
        field = None
        if step.uncertainty is not None:
            world = step.uncertainty.to_world(policy.action_normalizer)
            field = (world.samples, world.vectors, world.labels, world.arrow_scale())
        writer.write_step(
            frame.obs,
            {**step.command.to_dict(), "clamped": list(step.target.clamped)},
            step.action,
            label,
            frame.pos,
            frame.quat,
            step.scores.get("denoising"),
            shadow={k: v for k, v in step.scores.items() if k != "denoising"},
            field=field,
            images={c["name"]: frame.images[c["name"]] for c in writer.meta.get(keys.CAMERAS, [])},
        )

    def takeover_images(self, robot: Robot, images) -> None:
        """The camera views the operator saw (``server.cameras.CameraImages``), if a takeover is open."""
        writer = self._of(robot).takeover
        if writer is not None:
            for camera, jpeg in images.images.items():
                writer.write_image(camera, jpeg, images.t)

    def close_takeover(self, robot: Robot, ended_by: str) -> None:
        """Ends the robot's takeover, if one is open; ended_by: one of ``db.SEGMENT_ENDS``."""
        rec = self._of(robot)
        if rec.takeover is None:
            return
        writer, rec.takeover = rec.takeover, None
        writer.close("closed", ended_by)
        with self.sessions() as s:
            row = s.get(SegmentRecord, rec.takeover_id)
            if row is not None:
                row.status, row.ended_by, row.steps, row.ended_at = "closed", ended_by, writer.steps, datetime.now(UTC)
                s.commit()
        rec.takeover_id = None


@dataclass
class Recovered:
    segments: int = 0
    episodes: int = 0
    unreadable: int = 0  # files that held nothing readable (their rows are closed all the same)


def recover(sessions: sessionmaker, data_dir: Path) -> Recovered:
    """At start, before any robot runs: every segment left open by a crash is rewritten as a complete,
    indexed MCAP ending in ``recovered`` / ``crash-recovered`` and its row marked ``recovered``; every
    episode left open is closed as ``interrupted`` (its file, if recorded, rewritten the same way)."""
    out = Recovered()
    now = datetime.now(UTC)
    with sessions() as s:
        for row in s.scalars(select(SegmentRecord).where(SegmentRecord.status == "open")):
            try:
                row.steps = recover_segment(in_store(data_dir, row.path))
            except (SegmentReadError, OSError) as exc:
                log.warning("segment %d: %s", row.id, exc)
                row.steps, out.unreadable = 0, out.unreadable + 1
            row.status, row.ended_by, row.ended_at = "recovered", "crash-recovered", now
            out.segments += 1
        for ep in s.scalars(select(EpisodeRecord).where(EpisodeRecord.outcome.is_(None))):
            if ep.path is not None:
                try:
                    ep.steps = recover_episode(in_store(data_dir, ep.path))
                except (EpisodeReadError, OSError) as exc:
                    log.warning("episode %d: %s", ep.id, exc)
                    out.unreadable += 1
            ep.outcome, ep.ended_at = "interrupted", now
            out.episodes += 1
        s.commit()
    return out

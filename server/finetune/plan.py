"""What a fine-tuning job is asked, and what it would learn from: the request, and the plan that checks it.

Bad input is refused before anything is written: a request that does not validate (``JobRequest``), a
reference that names no version, a lineage with no closed or recovered takeover segments. Planning
reads the registry and the segment rows and writes nothing, so the API can check a request (and
answer 422) before it queues a job; ``server.finetune.job`` runs the plans.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from policy.finetune import FinetuneConfig
from server import registry
from server.db import EpisodeRecord, PolicyVersion, SegmentRecord
from server.errors import ServiceError
from server.labels import why_discarded
from storage.takeovers import TakeoverSelection

SOURCES = ("takeovers", "full-episodes")
USABLE = ("closed", "recovered")  # open segments are never used
_SINCE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhdw])\s*$")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 604800}


def parse_since(text: str) -> timedelta:
    """``30m``, ``24h``, ``7d``, ``2w`` as a timedelta (ValueError otherwise)."""
    m = _SINCE.match(text or "")
    if m is None or float(m[1]) <= 0:
        raise ValueError(f"--since {text!r}: expected a positive duration like 30m, 24h, 7d or 2w")
    try:
        return timedelta(seconds=float(m[1]) * _UNITS[m[2]])
    except OverflowError as exc:
        raise ValueError(f"--since {text!r}: too long") from exc


@dataclass(frozen=True)
class JobRequest:
    """policy: NAME, NAME@active or NAME@VERSION (None: every lineage with new takeover segments);
    since: only segments that ended this recently; source: ``takeovers`` or ``full-episodes`` (then
    ``episodes``: a folder of episode MCAPs); eval_tasks: the gate's target tasks (default: the tasks the
    takeovers came from); promote: promote a version that passes the gate; job_id: a queued job row to
    run (the API's trigger); selection: lineage -> (successful_only, takeover_tail), which takeovers that
    lineage learns from in place of ``config``'s (``[finetune.selection]``; ``config_for``)."""

    policy: str | None = None
    since: timedelta | None = None
    source: str = "takeovers"
    episodes: Path | None = None
    pretrain_data: Path | None = None
    eval_tasks: tuple[str, ...] | None = None
    promote: bool = True
    config: FinetuneConfig = field(default_factory=FinetuneConfig)
    trigger: str = "cli"
    command: str | None = None
    job_id: int | None = None
    lease_ttl: float = 60.0
    selection: dict[str, tuple[bool, int | None]] = field(default_factory=dict)

    def config_for(self, lineage: str) -> FinetuneConfig:
        """The training settings of one lineage's job: ``config``, with the lineage's own selection."""
        if lineage not in self.selection:
            return self.config
        successful_only, tail = self.selection[lineage]
        return replace(self.config, successful_only=successful_only, takeover_tail=tail)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.source == "full-episodes" and self.episodes is None:
            raise ValueError("--source full-episodes needs --episodes DIR (a folder of episode MCAP files)")
        if self.source == "full-episodes" and self.policy is None:
            raise ValueError("--source full-episodes needs --policy")


@dataclass
class Plan:
    """What one job will use: the parent version, and the segment rows or episode folder."""

    lineage: str
    parent: PolicyVersion
    segments: list[SegmentRecord]
    episodes: Path | None = None

    @property
    def segment_ids(self) -> list[int]:
        return [s.id for s in self.segments]


def plan_jobs(sessions: sessionmaker, request: JobRequest) -> list[Plan]:
    """One plan per lineage the request names (or, without a policy, per lineage with new segments);
    ServiceError for bad input. Validation only: nothing is written."""
    if request.policy is not None:
        parent = registry.resolve(sessions, request.policy)
        if request.source == "full-episodes":
            if not Path(request.episodes).is_dir():
                raise ServiceError(422, f"--episodes {request.episodes}: no such folder")
            return [Plan(parent.name, parent, [], Path(request.episodes))]
        segments = usable_segments(sessions, parent.name, request.since)
        if not segments:
            window = f" that ended in the last {request.since}" if request.since else ""
            raise ServiceError(
                422, f"policy {parent.name} has no closed or recovered takeover segments{window}: nothing to learn"
            )
        return [Plan(parent.name, parent, segments)]
    plans = []
    for name, active in sorted(registry.active_versions(sessions).items()):
        segments = usable_segments(sessions, name, request.since)
        # new: not in the manifest of any version of the lineage (a candidate the gate refused included,
        # so a refused run is not repeated every night on the same data)
        used = {
            i
            for v in registry.versions(sessions, name)
            for key in ("segment_ids", "skipped_segment_ids", "excluded_segment_ids")
            for i in (v.manifest or {}).get(key, [])
        }
        # news: what the selection would learn from (a takeover it leaves out starts no job; one whose
        # episode is still running is news once its episode has ended, if it succeeded)
        kept = {s.id for s in select_segments(sessions, segments, request.config_for(name).selection)[0]}
        if any(s.id not in used and s.id in kept for s in segments):
            plans.append(Plan(name, active, segments))
    return plans


def select_segments(
    sessions: sessionmaker, segments: list[SegmentRecord], selection: TakeoverSelection
) -> tuple[list[SegmentRecord], dict[int, str], list[SegmentRecord]]:
    """(kept, left out {segment id: why}, waiting: those whose episode has not ended) under
    ``selection``. A takeover an operator discarded is always left out (its flag is read now, not
    from the rows given, so a discard made while a job was queued applies); with ``successful_only``,
    so is one whose episode did not succeed."""
    ids = [s.id for s in segments]
    with sessions() as db:
        current = {row.id: row for row in db.scalars(select(SegmentRecord).where(SegmentRecord.id.in_(ids)))}
        db.expunge_all()
    left_out: dict[int, str] = {}
    candidates = []
    for seg in (current.get(s.id, s) for s in segments):  # as the rows stand now
        if (why := why_discarded(seg)) is not None:
            left_out[seg.id] = why
        else:
            candidates.append(seg)
    if not selection.successful_only:
        return candidates, left_out, []
    episode_ids = {s.episode_id for s in candidates if s.episode_id is not None}
    with sessions() as db:
        rows = db.execute(select(EpisodeRecord.id, EpisodeRecord.outcome).where(EpisodeRecord.id.in_(episode_ids)))
        outcomes = {i: outcome for i, outcome in rows}
    kept, waiting = [], []
    for seg in candidates:
        if seg.episode_id not in outcomes:
            left_out[seg.id] = "no episode recorded for it (successful episodes only)"
        elif outcomes[seg.episode_id] is None:
            waiting.append(seg)
        elif (why := selection.why_excluded(outcomes[seg.episode_id])) is not None:
            left_out[seg.id] = why
        else:
            kept.append(seg)
    return kept, left_out, waiting


def usable_segments(sessions: sessionmaker, lineage: str, since: timedelta | None) -> list[SegmentRecord]:
    """The lineage's closed or recovered takeover segments (those that ended within ``since``), by id."""
    ids = registry.lineage_ids(sessions, lineage)
    q = select(SegmentRecord).where(SegmentRecord.policy_id.in_(ids), SegmentRecord.status.in_(USABLE))
    if since is not None:
        q = q.where(SegmentRecord.ended_at >= datetime.now(UTC) - since)
    with sessions() as s:
        return list(s.scalars(q.order_by(SegmentRecord.id)))

"""Which of the fleet's episodes and takeovers an export takes, as ``storage.lerobot`` attempts.

``ExportQuery`` selects by task, lineage (every version of a policy name), time (started within
``since`` .. ``until``) and id (episodes, takeover segments). A selected episode whose whole file was
recorded (``record_episodes``) becomes one attempt with its takeovers inside it, frame by frame; a
selected takeover whose episode was not recorded, or every takeover with ``takeovers_only``, becomes an
attempt of its own. Each takeover carries its operator label and the request it answered
(``server.labels.label_of``: null numbers for a takeover recorded before they were stored). What
cannot be exported (no file, an unreadable one, an episode still running) is named in
``Collected.skipped`` with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import sessionmaker
from tqdm import tqdm

from server import registry
from server.db import EpisodeRecord, PolicyVersion, SegmentRecord
from server.errors import ServiceError
from server.finetune.plan import USABLE
from server.labels import label_of
from sim.registry import TASKS, make_task
from storage.episodes import EpisodeReadError, read_episode
from storage.lerobot.attempts import Attempt, from_episode, from_segment
from storage.paths import in_store
from storage.segments import SegmentReadError, read_segment


@dataclass(frozen=True)
class ExportQuery:
    task: str | None = None
    lineage: str | None = None
    since: datetime | None = None
    until: datetime | None = None
    episode_ids: tuple[int, ...] = ()
    segment_ids: tuple[int, ...] = ()
    takeovers_only: bool = False


@dataclass
class Collected:
    attempts: list[Attempt] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # "episode 12" / "segment 4" -> why


def _filtered(q, model, query: ExportQuery, policy_ids: list[int] | None):
    if query.task is not None:
        q = q.where(model.task == query.task)
    if policy_ids is not None:
        q = q.where(model.policy_id.in_(policy_ids))
    if query.since is not None:
        q = q.where(model.started_at >= query.since)
    if query.until is not None:
        q = q.where(model.started_at < query.until)
    return q


def collect(sessions: sessionmaker, data_dir: Path, query: ExportQuery, progress: bool = True) -> Collected:
    """The attempts ``query`` selects, in the order the fleet recorded them."""
    policy_ids = None
    if query.lineage is not None:
        policy_ids = registry.lineage_ids(sessions, query.lineage)
        if not policy_ids:
            raise ServiceError(404, f"no policy named {query.lineage!r}")
    seg_q = _filtered(select(SegmentRecord).where(SegmentRecord.status.in_(USABLE)), SegmentRecord, query, policy_ids)
    ep_q = _filtered(select(EpisodeRecord), EpisodeRecord, query, policy_ids)
    if query.episode_ids:
        ep_q = ep_q.where(EpisodeRecord.id.in_(query.episode_ids))
        seg_q = seg_q.where(SegmentRecord.episode_id.in_(query.episode_ids))
    if query.segment_ids:
        seg_q = seg_q.where(SegmentRecord.id.in_(query.segment_ids))
        if not query.episode_ids:
            ep_q = ep_q.where(
                EpisodeRecord.id.in_(select(SegmentRecord.episode_id).where(SegmentRecord.id.in_(query.segment_ids)))
            )
    with sessions() as s:
        segments = list(s.scalars(seg_q.order_by(SegmentRecord.id)))
        episodes = [] if query.takeovers_only else list(s.scalars(ep_q.order_by(EpisodeRecord.id)))
        refs = {p.id: p.ref for p in s.scalars(select(PolicyVersion))}
        # every takeover inside an exported episode carries its label, selected or not
        ids = [e.id for e in episodes]
        inside = list(s.scalars(select(SegmentRecord).where(SegmentRecord.episode_id.in_(ids)))) if ids else []
    labels_by_episode: dict[int, dict] = {}
    for seg in inside:
        labels_by_episode.setdefault(seg.episode_id, {})[seg.id] = label_of(seg)

    out = Collected()
    whole: set[int] = set()
    with_takeovers = {seg.episode_id for seg in segments}
    for ep in tqdm(episodes, desc="episodes", unit="ep", disable=not progress):
        name = f"episode {ep.id}"
        if ep.outcome is None:
            out.skipped[name] = "still running"
            continue
        if ep.path is None:
            if ep.id not in with_takeovers:
                out.skipped[name] = "its file was not recorded (record_episodes is off); no takeover in it"
            continue
        try:
            recorded = read_episode(in_store(data_dir, ep.path))
        except (EpisodeReadError, OSError) as exc:
            out.skipped[name] = f"unreadable ({exc}); its takeovers are exported alone"
            continue
        meta = {"fleet_episode": ep.id, "outcome": ep.outcome, "policy": refs.get(ep.policy_id)}
        out.attempts.append(from_episode(recorded, labels_by_episode.get(ep.id, {}), meta))
        whole.add(ep.id)
    for seg in tqdm(segments, desc="takeovers", unit="seg", disable=not progress):
        if seg.episode_id in whole:
            continue
        try:
            recorded = read_segment(in_store(data_dir, seg.path))
            recorded.steps  # noqa: B018 - parsed here: a malformed step skips the segment like an unreadable file
        except (SegmentReadError, OSError) as exc:
            out.skipped[f"segment {seg.id}"] = f"unreadable ({exc})"
            continue
        meta = {"fleet_episode": seg.episode_id, "policy": refs.get(seg.policy_id), "operator": seg.operator}
        attempt = from_segment(recorded, seg.id, label_of(seg), meta)
        if not attempt.obs_labels and seg.task in TASKS:  # an older segment does not name its channels; its task does
            attempt.obs_labels = make_task(seg.task).obs_spec.labels()
        out.attempts.append(attempt)
    return out

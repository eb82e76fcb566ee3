"""The human effort a policy version needs: what the console's lineage view shows of each version, and
of each day of the fleet it serves.

Counted over episodes that ended on their own (success or timeout: ``server.fleet.recording.FINISHED``),
grouped in the database (one ``GROUP BY`` per view, however many episodes): episodes, successes,
autonomous successes (episodes that asked nothing), requests and assisted steps. A day is the
database's calendar date of the episode's start (UTC).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from sqlalchemy import and_, case, func, select
from sqlalchemy.orm import Session

from server.db import FINISHED, EpisodeRecord


@dataclass(frozen=True)
class Effort:
    """One version's (or one day's) episodes and the help they took."""

    episodes: int = 0
    successes: int = 0
    autonomous_successes: int = 0
    requests: int = 0
    assisted_steps: int = 0

    def __add__(self, other: Effort) -> Effort:
        return Effort(*(a + b for a, b in zip(self.row(), other.row(), strict=True)))

    def row(self) -> tuple[int, ...]:
        return (self.episodes, self.successes, self.autonomous_successes, self.requests, self.assisted_steps)

    @property
    def autonomous_rate(self) -> float | None:
        return self.autonomous_successes / self.episodes if self.episodes else None

    @property
    def assisted_steps_per_episode(self) -> float | None:
        return self.assisted_steps / self.episodes if self.episodes else None

    @property
    def requests_per_episode(self) -> float | None:
        return self.requests / self.episodes if self.episodes else None


def _sums():
    alone = and_(EpisodeRecord.outcome == "success", EpisodeRecord.assistance_events == 0)
    return (
        func.count(EpisodeRecord.id),
        func.sum(case((EpisodeRecord.outcome == "success", 1), else_=0)),
        func.sum(case((alone, 1), else_=0)),
        func.sum(EpisodeRecord.assistance_events),
        func.sum(EpisodeRecord.assisted_steps),
    )


def by_version(s: Session) -> dict[int, Effort]:
    """policy version id -> the effort of its finished episodes."""
    q = select(EpisodeRecord.policy_id, *_sums()).where(EpisodeRecord.outcome.in_(FINISHED))
    rows = s.execute(q.group_by(EpisodeRecord.policy_id)).all()
    return {r[0]: Effort(*(int(v or 0) for v in r[1:])) for r in rows if r[0] is not None}


def by_day(s: Session, days: int = 7, now: datetime | None = None) -> dict[tuple[int, str], Effort]:
    """(policy version id, ISO date) -> the effort of the finished episodes that started that day, for
    the last ``days`` days."""
    since = (now or datetime.now(UTC)) - timedelta(days=days)
    day = func.date(EpisodeRecord.started_at)
    q = select(EpisodeRecord.policy_id, day, *_sums()).where(
        EpisodeRecord.outcome.in_(FINISHED), EpisodeRecord.started_at >= since
    )
    rows = s.execute(q.group_by(EpisodeRecord.policy_id, day)).all()
    return {(r[0], str(r[1])): Effort(*(int(v or 0) for v in r[2:])) for r in rows if r[0] is not None}

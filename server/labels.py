"""Operator labels on takeovers: good or bad, discarded, a short note; who set them and when.

A label lives on the takeover's row (``db.SegmentRecord``: migration 0006). Setting one changes only
the fields given (a note can be added without touching the verdict) and records the operator and the
time of the change. Discarding keeps the MCAP file (it can still be downloaded and exported) and takes
the takeover out of every fine-tuning selection (``server.finetune.plan.select_segments``), which
records it as excluded, with the reason, in the job's manifest. A takeover still being recorded can be
labelled too: the verdict usually comes right at the hand-back.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy.orm import sessionmaker

from server.db import NOTE_MAX, SEGMENT_LABELS, SegmentRecord
from server.errors import ServiceError
from storage.lerobot.attempts import TakeoverLabel, TakeoverRequest

DISCARDED_WHY = "discarded by {who} at {when}"


@dataclass(frozen=True)
class LabelChange:
    """The fields to change; None leaves a field as it is. ``clear_label``: remove the good/bad verdict;
    an empty ``note`` removes the note."""

    label: str | None = None
    clear_label: bool = False
    discarded: bool | None = None
    note: str | None = None

    def __post_init__(self) -> None:
        if self.label is not None and self.label not in SEGMENT_LABELS:
            raise ServiceError(422, f"label must be one of {SEGMENT_LABELS} (or null to clear it), got {self.label!r}")
        if self.note is not None and len(self.note) > NOTE_MAX:
            raise ServiceError(422, f"a note is at most {NOTE_MAX} characters, got {len(self.note)}")
        if self.note is not None and "\x00" in self.note:
            raise ServiceError(422, "a note cannot hold a NUL character")

    @property
    def empty(self) -> bool:
        return self.label is None and not self.clear_label and self.discarded is None and self.note is None


def set_label(sessions: sessionmaker, segment_id: int, who: str, change: LabelChange) -> SegmentRecord:
    """Applies ``change`` to the takeover and returns its row; raises ServiceError (404, 422)."""
    if change.empty:
        raise ServiceError(422, "nothing to change: give label, discarded or note")
    with sessions() as s:
        row = s.get(SegmentRecord, segment_id)
        if row is None:
            raise ServiceError(404, f"no takeover segment {segment_id}")
        if change.label is not None or change.clear_label:
            row.label = change.label
        if change.discarded is not None:
            row.discarded = change.discarded
        if change.note is not None:
            row.note = change.note.strip() or None
        row.labelled_by, row.labelled_at = who, datetime.now(UTC)
        s.commit()
        s.refresh(row)
        s.expunge(row)
        return row


def label_of(row: SegmentRecord) -> TakeoverLabel:
    """The takeover's label and the request it answered (None where a row recorded before migration 0007
    has none)."""
    request = TakeoverRequest(row.signal, row.score, row.threshold, row.reason, row.paper_u)
    return TakeoverLabel(row.label, bool(row.discarded), row.note, row.labelled_by, row.labelled_at, request)


def why_discarded(row: SegmentRecord) -> str | None:
    """Why a fine-tuning selection leaves the takeover out, or None when it is not discarded."""
    if not row.discarded:
        return None
    when = row.labelled_at.isoformat(timespec="seconds") if row.labelled_at else "an unknown time"
    return DISCARDED_WHY.format(who=row.labelled_by or "an operator", when=when)

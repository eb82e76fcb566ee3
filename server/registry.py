"""The policy registry: versions of each policy lineage in the database, their files on disk.

A lineage is a name (``lift-cube``); its versions are numbered 1, 2, ... and addressed as
``NAME@VERSION``, ``NAME@active`` or just ``NAME`` (its active version). At most one version of a
lineage is ``active``; ``promote`` makes one active and retires the one it replaces; ``rollback``
returns to the active version's parent. The registry is the source of truth: a running fleet follows
it (``Fleet.sync_policies``), so ``hitl policy promote`` from a shell and the admin API hot-swap the
same way, at each robot's next episode.

Every function raises ``ServiceError`` (404 unknown name or version, 409 a state that does not
allow it, 422 a version whose files are unusable) and changes nothing when it does.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from policy.checkpoint import CheckpointError, read_info
from server import effort
from server.db import FinetuneJob, PolicyVersion
from server.effort import Effort
from server.errors import ServiceError
from server.lease import Lease, renew_in
from storage import paths

_REF = re.compile(r"^(?P<name>[A-Za-z0-9][A-Za-z0-9._-]{0,255})(?:@(?P<sel>active|[1-9][0-9]{0,8}))?$")


@dataclass(frozen=True)
class PolicyRef:
    """name: the lineage; version: a number, or None for the active version."""

    name: str
    version: int | None = None

    @classmethod
    def parse(cls, text: str) -> PolicyRef:
        m = _REF.match(text.strip()) if isinstance(text, str) else None
        if m is None:
            raise ServiceError(422, f"bad policy reference {text!r}: expected NAME, NAME@active or NAME@VERSION")
        sel = m["sel"]
        return cls(m["name"], None if sel in (None, "active") else int(sel))

    def __str__(self) -> str:
        return f"{self.name}@{'active' if self.version is None else self.version}"


def _names(s: Session) -> list[str]:
    return list(s.scalars(select(PolicyVersion.name).distinct().order_by(PolicyVersion.name)))


def find(s: Session, ref: PolicyRef) -> PolicyVersion:
    """The version ``ref`` names, inside session ``s`` (ServiceError 404 otherwise)."""
    q = select(PolicyVersion).where(PolicyVersion.name == ref.name)
    if ref.version is None:
        row = s.scalars(q.where(PolicyVersion.status == "active")).first()
        if row is None:
            if s.scalars(q).first() is None:
                raise ServiceError(404, _unknown(s, ref.name))
            raise ServiceError(404, f"policy {ref.name} has no active version: promote one")
        return row
    row = s.scalars(q.where(PolicyVersion.version == ref.version)).one_or_none()
    if row is None:
        raise ServiceError(404, _unknown(s, ref.name) if s.scalars(q).first() is None else f"no policy {ref}")
    return row


def _unknown(s: Session, name: str) -> str:
    known = _names(s)
    return f"no policy named {name!r}" + (f"; registered: {', '.join(known)}" if known else "; none is registered")


def resolve(sessions: sessionmaker, ref: str | PolicyRef) -> PolicyVersion:
    ref = PolicyRef.parse(ref) if isinstance(ref, str) else ref
    with sessions() as s:
        return find(s, ref)


def by_id(sessions: sessionmaker, version_id: int) -> PolicyVersion:
    with sessions() as s:
        row = s.get(PolicyVersion, version_id)
        if row is None:
            raise ServiceError(404, f"no policy version {version_id}")
        return row


def versions(sessions: sessionmaker, name: str | None = None) -> list[PolicyVersion]:
    q = select(PolicyVersion).order_by(PolicyVersion.name, PolicyVersion.version)
    with sessions() as s:
        if name is not None:
            rows = list(s.scalars(q.where(PolicyVersion.name == name)))
            if not rows:
                raise ServiceError(404, _unknown(s, name))
            return rows
        return list(s.scalars(q))


def lineage_ids(sessions: sessionmaker, name: str) -> list[int]:
    with sessions() as s:
        return list(s.scalars(select(PolicyVersion.id).where(PolicyVersion.name == name)))


def active_versions(sessions: sessionmaker) -> dict[str, PolicyVersion]:
    """lineage -> its active version."""
    with sessions() as s:
        return {r.name: r for r in s.scalars(select(PolicyVersion).where(PolicyVersion.status == "active"))}


def folder(row: PolicyVersion) -> Path:
    """A version's folder as this process opens it: the registry records it relative to the data root
    (``storage.paths``) when it lies under it, so a database names no machine's folders."""
    return paths.resolve(row.path)


def path_keys(path: str | Path) -> list[str]:
    """How the registry may record a folder: relative to the data root (new rows), or absolute (rows
    registered before paths were recorded relative)."""
    absolute = str(Path(path).resolve())
    return list(dict.fromkeys([paths.portable(absolute), absolute]))


def by_path(s: Session, path: str | Path) -> PolicyVersion | None:
    """The version registered for a folder, if any."""
    return s.scalars(select(PolicyVersion).where(PolicyVersion.path.in_(path_keys(path)))).first()


def _check_files(row: PolicyVersion) -> None:
    try:
        read_info(folder(row))
    except CheckpointError as exc:
        raise ServiceError(422, f"policy {row.ref}: {exc}") from exc
    if not (folder(row) / "model.safetensors").is_file():
        raise ServiceError(422, f"policy {row.ref}: {row.path}/model.safetensors not found")


def register(
    sessions: sessionmaker,
    path: str | Path,
    task: str,
    name: str | None = None,
    parent: int | None = None,
    status: str = "candidate",
    lease: Lease | None = None,
    **fields,
) -> PolicyVersion:
    """A new version of lineage ``name`` (default: the parent's lineage, else the folder's name), numbered
    one above its lineage's last; the same folder again returns the version already registered.

    lease: a fenced write (the fine-tuning job's): the version is written in the same transaction that
    renews the lease, or not at all (LeaseLost)."""
    key = path_keys(path)[0]
    with sessions() as s:
        if lease is not None:
            renew_in(s, lease)
        parent_row = s.get(PolicyVersion, parent) if parent is not None else None
        if parent is not None and parent_row is None:
            raise ServiceError(404, f"no policy version {parent}")
        row = by_path(s, path)
        if row is not None:
            return row
        lineage = name or (parent_row.name if parent_row is not None else Path(path).resolve().name)
        if PolicyRef.parse(lineage) != PolicyRef(lineage):  # e.g. a folder named "x@3"
            raise ServiceError(422, f"{lineage!r} cannot name a policy: NAME@VERSION could not address it")
        last = s.scalar(select(func.max(PolicyVersion.version)).where(PolicyVersion.name == lineage)) or 0
        row = PolicyVersion(
            name=lineage, version=last + 1, path=key, task=task, status=status, parent_id=parent, **fields
        )
        s.add(row)
        _commit(s, f"another version of {lineage} was registered at the same time: try again")
        return row


def promote(
    sessions: sessionmaker, ref: str | PolicyRef | int, reason: str | None = None, lease: Lease | None = None
) -> PolicyVersion:
    """Makes the version active and retires the lineage's previously active one (``lease``: a fenced
    write, as in ``register``)."""
    with sessions() as s:
        if lease is not None:
            renew_in(s, lease)
        row = s.get(PolicyVersion, ref) if isinstance(ref, int) else find(s, _ref(ref))
        if row is None:
            raise ServiceError(404, f"no policy version {ref}")
        _check_files(row)
        for other in s.scalars(
            select(PolicyVersion).where(PolicyVersion.name == row.name, PolicyVersion.status == "active")
        ):
            if other.id != row.id:
                other.status, other.status_reason = "retired", f"replaced by {row.ref}"
        s.flush()  # the retirement first: one active version per lineage is a unique index
        row.status = "active"
        row.status_reason = reason or "promoted"
        _commit(s, f"{row.name} was promoted or rolled back at the same time: try again")
        return row


def rollback(sessions: sessionmaker, name: str, reason: str | None = None) -> PolicyVersion:
    """Retires the lineage's active version and makes its parent active again; returns the parent."""
    with sessions() as s:
        active = find(s, PolicyRef(name))
        if active.parent_id is None:
            raise ServiceError(409, f"policy {active.ref} has no parent version to roll back to")
        parent = s.get(PolicyVersion, active.parent_id)
        if parent.name != name:
            raise ServiceError(409, f"the parent of {active.ref} is {parent.ref}, another lineage: promote it instead")
        _check_files(parent)
        active.status, active.status_reason = "retired", reason or f"rolled back to {parent.ref}"
        s.flush()
        parent.status, parent.status_reason = "active", reason or f"rollback from {active.ref}"
        _commit(s, f"{name} was promoted or rolled back at the same time: try again")
        return parent


def _commit(s: Session, conflict: str) -> None:
    """Commits; a unique index broken by a concurrent writer is a 409 and nothing of this one is kept."""
    try:
        s.commit()
    except IntegrityError as exc:
        s.rollback()
        raise ServiceError(409, conflict) from exc


def _ref(ref: str | PolicyRef) -> PolicyRef:
    return PolicyRef.parse(ref) if isinstance(ref, str) else ref


def last_jobs(sessions: sessionmaker) -> dict[str, FinetuneJob]:
    """lineage -> its most recent fine-tuning job."""
    with sessions() as s:
        newest = select(FinetuneJob.lineage, func.max(FinetuneJob.id).label("id")).group_by(FinetuneJob.lineage)
        ids = [r.id for r in s.execute(newest)]
        return {j.lineage: j for j in s.scalars(select(FinetuneJob).where(FinetuneJob.id.in_(ids)))} if ids else {}


@dataclass(frozen=True)
class LineageSummary:
    """What the console shows of a lineage: its active version, where it came from, its last job."""

    name: str
    active: str | None  # NAME@VERSION
    reason: str | None
    parent: str | None
    versions: int
    candidates: int
    job_id: int | None = None
    job_status: str | None = None
    job_stage: str | None = None
    job_progress: float = 0.0
    job_gate: str | None = None
    job_promoted: bool | None = None
    job_error: str | None = None
    job_ended: str | None = None  # ISO time
    history: tuple[VersionHistory, ...] = ()  # every version, oldest first
    days: tuple[tuple[str, Effort], ...] = ()  # (ISO date, the lineage's effort that day), the last 7 days


@dataclass(frozen=True)
class VersionHistory:
    """One version of a lineage as the console's lineage view lists it: why it has its status (the
    gate's decision for a fine-tuned one) and the effort of the episodes it served."""

    ref: str
    status: str
    reason: str | None
    created: str  # ISO time
    effort: Effort


def lineage_summaries(sessions: sessionmaker) -> list[LineageSummary]:
    rows = versions(sessions)
    jobs = last_jobs(sessions)
    with sessions() as s:
        per_version, per_day = effort.by_version(s), effort.by_day(s)
    by_id = {r.id: r for r in rows}
    out = []
    for name in sorted({r.name for r in rows}):
        mine = [r for r in rows if r.name == name]
        active = next((r for r in mine if r.status == "active"), None)
        parent = by_id.get(active.parent_id) if active is not None and active.parent_id is not None else None
        job = jobs.get(name)
        gate = (job.gate or {}) if job is not None else {}
        out.append(
            LineageSummary(
                name=name,
                active=active.ref if active else None,
                reason=active.status_reason if active else None,
                parent=parent.ref if parent else None,
                versions=len(mine),
                candidates=sum(r.status == "candidate" for r in mine),
                job_id=job.id if job else None,
                job_status=job.status if job else None,
                job_stage=job.stage if job else None,
                job_progress=float(job.progress or 0.0) if job else 0.0,
                job_gate=gate.get("reason"),
                job_promoted=gate.get("promoted"),
                job_error=job.error if job else None,
                job_ended=job.ended_at.isoformat(timespec="minutes") if job and job.ended_at else None,
                history=tuple(
                    VersionHistory(
                        r.ref,
                        r.status,
                        r.status_reason,
                        r.created_at.isoformat(timespec="minutes"),
                        per_version.get(r.id, Effort()),
                    )
                    for r in sorted(mine, key=lambda r: r.version)
                ),
                days=_lineage_days({r.id for r in mine}, per_day),
            )
        )
    return out


def _lineage_days(ids: set[int], per_day: dict[tuple[int, str], Effort]) -> tuple[tuple[str, Effort], ...]:
    days: dict[str, Effort] = {}
    for (version_id, day), e in per_day.items():
        if version_id in ids:
            days[day] = days.get(day, Effort()) + e
    return tuple(sorted(days.items()))


class LineageCache:
    """``lineage_summaries`` read from the database at most every ``max_age`` seconds (what the console
    shows); a database hiccup keeps the last view and is tried again later."""

    def __init__(self, sessions: sessionmaker) -> None:
        self.sessions = sessions
        self._last: tuple[float, tuple[LineageSummary, ...]] | None = None  # (when read, summaries)

    def get(self, max_age: float = 5.0) -> tuple[LineageSummary, ...]:
        now = time.monotonic()
        if self._last is None or now - self._last[0] > max_age:
            try:
                self._last = (now, tuple(lineage_summaries(self.sessions)))
            except Exception:  # noqa: BLE001 - a database hiccup: the last view, tried again later
                logging.getLogger("hitl.registry").warning("reading the policy registry failed", exc_info=True)
                self._last = (now, self._last[1] if self._last else ())
        return self._last[1]

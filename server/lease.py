"""A named lease in the database: at most one holder at a time, across processes and machines.

``SELECT ... FOR UPDATE`` is a no-op on SQLite, so acquisition is one conditional ``UPDATE``: it takes
the row only when nobody holds it or the holder's lease has expired, and bumps a fencing counter.
Expiry is decided by the database's clock (``server.db.db_epoch``), never by the callers' clocks. A
holder renews with ``renew``; a holder that crashed simply stops renewing, and its lease lapses after
``ttl`` seconds. ``renew`` and ``release`` match on the fence too, so a holder whose lease lapsed and
was taken over learns it (``LeaseLost``) instead of writing as if it still held it.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from sqlalchemy import and_, case, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from server.db import JobLease, db_epoch

log = logging.getLogger("hitl.lease")

FINETUNE_LEASE = "finetune"


class LeaseLost(RuntimeError):
    """The lease lapsed and another holder took it (or it was released): stop and write nothing."""


@dataclass(frozen=True)
class Lease:
    name: str
    owner: str
    fence: int
    ttl: float


def _ensure_row(sessions: sessionmaker, name: str) -> None:
    with sessions() as s:
        if s.get(JobLease, name) is not None:
            return
        try:
            s.execute(insert(JobLease).values(name=name, owner=None, fence=0, expires_at=0.0))
            s.commit()
        except IntegrityError:  # another process inserted it first
            s.rollback()


def acquire(sessions: sessionmaker, name: str, owner: str, ttl: float, reentrant: bool = False) -> Lease | None:
    """The lease, or None when someone else holds a lease that has not expired.

    reentrant: an owner that already holds the lease gets it again, renewed, with the same fence (an
    operator claiming from a second browser tab is still the one holder); otherwise it is refused too."""
    if ttl <= 0:
        raise ValueError(f"ttl must be > 0, got {ttl!r}")
    _ensure_row(sessions, name)
    free = or_(JobLease.owner.is_(None), JobLease.expires_at < db_epoch())
    mine = and_(JobLease.owner == owner, JobLease.expires_at >= db_epoch())
    with sessions() as s:
        done = s.execute(
            update(JobLease)
            .where(JobLease.name == name, or_(free, mine) if reentrant else free)
            .values(
                owner=owner,
                fence=case((mine, JobLease.fence), else_=JobLease.fence + 1) if reentrant else JobLease.fence + 1,
                expires_at=db_epoch() + ttl,
            )
            .execution_options(synchronize_session=False)
        )
        s.commit()
        if done.rowcount != 1:
            return None
        fence = s.scalar(select(JobLease.fence).where(JobLease.name == name, JobLease.owner == owner))
    return Lease(name, owner, int(fence), ttl)


def _held(lease: Lease):
    return and_(JobLease.name == lease.name, JobLease.owner == lease.owner, JobLease.fence == lease.fence)


def renew(sessions: sessionmaker, lease: Lease) -> None:
    """Extends the lease by its ttl from now (the database's now); LeaseLost if it is no longer held."""
    with sessions() as s:
        renew_in(s, lease)
        s.commit()


def renew_in(s: Session, lease: Lease) -> None:
    """``renew`` inside the caller's transaction, for a write that must happen only under the lease (a
    fenced write): the caller commits both together, or rolls both back on LeaseLost. The update locks
    the lease's row until that commit (PostgreSQL; SQLite holds its write lock), so no other holder can
    take the lease between this check and the write."""
    done = s.execute(
        update(JobLease)
        .where(_held(lease), JobLease.expires_at >= db_epoch())
        .values(expires_at=db_epoch() + lease.ttl)
        .execution_options(synchronize_session=False)
    )
    if done.rowcount != 1:
        s.rollback()
        raise LeaseLost(f"lease {lease.name!r} (fence {lease.fence}) is no longer held by {lease.owner}")


def release(sessions: sessionmaker, lease: Lease) -> bool:
    """Gives the lease up if still held; False when it had already lapsed or been taken."""
    with sessions() as s:
        done = s.execute(
            update(JobLease)
            .where(_held(lease))
            .values(owner=None, expires_at=0.0)
            .execution_options(synchronize_session=False)
        )
        s.commit()
    return done.rowcount == 1


def holder(sessions: sessionmaker, name: str) -> tuple[str | None, float | None]:
    """(owner, seconds left by the database's clock), or (None, None) when free or expired."""
    with sessions() as s:
        row = s.execute(select(JobLease.owner, JobLease.expires_at - db_epoch()).where(JobLease.name == name)).first()
    if row is None or row[0] is None or row[1] < 0:
        return None, None
    return row[0], float(row[1])


class Heartbeat:
    """Renews ``lease`` every ``ttl / 3`` seconds in a thread; ``lost`` is set if a renewal fails."""

    def __init__(self, sessions: sessionmaker, lease: Lease) -> None:
        self.sessions, self.lease = sessions, lease
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{lease.name}", daemon=True)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.lease.ttl / 3):
            try:
                renew(self.sessions, self.lease)
            except LeaseLost as exc:
                log.error("%s", exc)
                self.lost.set()
                return
            except Exception:  # noqa: BLE001 - a database hiccup: try again at the next beat
                log.warning("lease %s: renewal failed, retrying", self.lease.name, exc_info=True)

    def check(self) -> None:
        """Raises LeaseLost if the heartbeat lost the lease, else renews once now (before a write)."""
        if self.lost.is_set():
            raise LeaseLost(f"lease {self.lease.name!r} was lost")
        renew(self.sessions, self.lease)

"""Console log-in sessions: an HttpOnly cookie carries a random session id; the hash of the API token
it was opened with stays on the server, so every use re-checks the token (revocation applies) and
log-out ends the session at once.

Two stores with the same three methods: ``ConsoleSessions`` in memory, for a service in one process
(a restart logs everyone out), and ``SharedConsoleSessions`` in the database, for API processes
apart from the fleet runtime (``service.replicas``): a browser logged in through one of them
is logged in at every other, whichever one the load balancer picks for its next request. The
database keeps only hashes: of the session id and of the token."""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from dataclasses import dataclass

from sqlalchemy import delete, select
from sqlalchemy.orm import sessionmaker

from server.auth import hash_token
from server.db import ConsoleSession, db_epoch

COOKIE = "hitl_console"
COOKIE_PATH = "/console"  # matches /console (the socket) and everything under /console/
MAX_AGE_S = 12 * 3600  # one shift


@dataclass(frozen=True)
class Session:
    token_hash: str
    opened: float


class ConsoleSessions:
    def __init__(self, max_age_s: float = MAX_AGE_S) -> None:
        self.max_age_s = max_age_s
        self._open: dict[str, Session] = {}
        self._lock = threading.Lock()

    def open(self, token: str) -> str:
        """A new session for an API token already checked by the caller; returns its id."""
        sid = secrets.token_urlsafe(32)
        with self._lock:
            self._open[sid] = Session(hash_token(token), time.monotonic())
        return sid

    def token_hash(self, sid: str | None) -> str | None:
        """The API token's hash behind a live session, or None (unknown, closed or older than ``max_age_s``)."""
        if not sid:
            return None
        with self._lock:
            s = self._open.get(sid)
            if s is not None and time.monotonic() - s.opened > self.max_age_s:
                del self._open[sid]
                s = None
        return s.token_hash if s else None

    def close(self, sid: str | None) -> None:
        with self._lock:
            self._open.pop(sid or "", None)


def _sid_hash(sid: str) -> str:
    return hashlib.sha256(sid.encode()).hexdigest()


class SharedConsoleSessions:
    """``ConsoleSessions`` in the database (``console_sessions``), ages by the database's clock."""

    def __init__(self, sessions: sessionmaker, max_age_s: float = MAX_AGE_S) -> None:
        self.sessions, self.max_age_s = sessions, max_age_s

    def open(self, token: str) -> str:
        sid = secrets.token_urlsafe(32)
        with self.sessions() as s:
            s.execute(delete(ConsoleSession).where(ConsoleSession.opened_at < db_epoch() - self.max_age_s))
            s.add(
                ConsoleSession(
                    sid_hash=_sid_hash(sid), token_hash=hash_token(token), opened_at=s.scalar(select(db_epoch()))
                )
            )
            s.commit()
        return sid

    def token_hash(self, sid: str | None) -> str | None:
        if not sid:
            return None
        with self.sessions() as s:
            return s.scalar(
                select(ConsoleSession.token_hash).where(
                    ConsoleSession.sid_hash == _sid_hash(sid), ConsoleSession.opened_at >= db_epoch() - self.max_age_s
                )
            )

    def close(self, sid: str | None) -> None:
        if not sid:
            return
        with self.sessions() as s:
            s.execute(delete(ConsoleSession).where(ConsoleSession.sid_hash == _sid_hash(sid)))
            s.commit()

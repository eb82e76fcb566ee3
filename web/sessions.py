"""Console log-in sessions: an HttpOnly cookie carries a random session id; the API token it was
opened with stays on the server, so every use re-checks the token (revocation applies) and log-out
ends the session at once. In memory, per service process: a restart logs everyone out. A shared
store (the database, Redis) can implement the same three methods when the service scales out."""

from __future__ import annotations

import secrets
import threading
import time
from dataclasses import dataclass

COOKIE = "hitl_console"
COOKIE_PATH = "/console"  # matches /console (the socket) and everything under /console/
MAX_AGE_S = 12 * 3600  # one shift


@dataclass(frozen=True)
class Session:
    token: str
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
            self._open[sid] = Session(token, time.monotonic())
        return sid

    def token(self, sid: str | None) -> str | None:
        """The API token behind a live session, or None (unknown, closed or older than ``max_age_s``)."""
        if not sid:
            return None
        with self._lock:
            s = self._open.get(sid)
            if s is not None and time.monotonic() - s.opened > self.max_age_s:
                del self._open[sid]
                s = None
        return s.token if s else None

    def close(self, sid: str | None) -> None:
        with self._lock:
            self._open.pop(sid or "", None)

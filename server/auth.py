"""API tokens: roles ``viewer`` < ``operator`` < ``admin``; shown once, stored as SHA-256 hashes.

Tokens are random (256 bits), so a plain hash is enough; they are never logged.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import sessionmaker

from server.db import ApiToken

ROLES = ("viewer", "operator", "admin")
PREFIX = "hitl_"


@dataclass(frozen=True)
class Principal:
    name: str
    role: str

    def has(self, role: str) -> bool:
        return ROLES.index(self.role) >= ROLES.index(role)


def forbidden(role: str, given: str) -> str:
    """What a refusal for the lack of ``role`` says to someone who has ``given`` (the API and the console)."""
    return f"this needs the {role} role; your token is {given}"


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def create_token(sessions: sessionmaker, name: str, role: str) -> str:
    """Creates a token and returns it (the only time it is visible)."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got {role!r}")
    if not name or len(name) > 128:
        raise ValueError("token name must be 1-128 characters")
    token = PREFIX + secrets.token_urlsafe(32)
    with sessions() as s:
        s.add(ApiToken(name=name, role=role, token_hash=hash_token(token)))
        try:
            s.commit()
        except IntegrityError as exc:
            raise ValueError(f"a token named {name!r} already exists") from exc
    return token


def revoke_token(sessions: sessionmaker, name: str) -> bool:
    with sessions() as s:
        row = s.scalar(select(ApiToken).where(ApiToken.name == name))
        if row is None:
            return False
        row.revoked = True
        s.commit()
        return True


def authenticate(sessions: sessionmaker, token: str | None) -> Principal | None:
    return authenticate_hash(sessions, hash_token(token)) if token else None


def authenticate_hash(sessions: sessionmaker, token_hash: str) -> Principal | None:
    """The principal of the unrevoked token with this hash (a console session keeps only the hash)."""
    with sessions() as s:
        row = s.scalar(select(ApiToken).where(ApiToken.token_hash == token_hash, ApiToken.revoked.is_(False)))
        return Principal(row.name, row.role) if row else None


class TokenCache:
    """``authenticate`` with answers kept for ``ttl`` seconds, so that polling clients do not cost a
    database query per request. A revocation (``hitl token revoke``, another process) takes effect for
    new requests within ``ttl``; an open WebSocket was authenticated once, at its handshake. At most
    ``max_entries`` tokens are kept, least recently used first out; unknown tokens are not cached."""

    def __init__(self, sessions: sessionmaker, ttl: float = 5.0, max_entries: int = 10_000) -> None:
        self.sessions, self.ttl, self.max_entries = sessions, ttl, max_entries
        self._seen: OrderedDict[str, tuple[float, Principal]] = OrderedDict()
        self._lock = threading.Lock()

    def cached(self, token: str | None) -> tuple[bool, Principal | None]:
        """(known, principal) without touching the database: known is False when ``authenticate`` must
        ask it."""
        return self.cached_hash(hash_token(token)) if token else (True, None)

    def cached_hash(self, key: str) -> tuple[bool, Principal | None]:
        with self._lock:
            hit = self._seen.get(key)
            if hit is None or time.monotonic() - hit[0] >= self.ttl:
                return False, None
            self._seen.move_to_end(key)
            return True, hit[1]

    def authenticate(self, token: str | None) -> Principal | None:
        """Asks the database (blocking) and remembers a valid token's principal."""
        return self.authenticate_hash(hash_token(token)) if token else None

    def authenticate_hash(self, key: str) -> Principal | None:
        principal = authenticate_hash(self.sessions, key)
        if principal is not None:
            with self._lock:
                self._seen[key] = (time.monotonic(), principal)
                self._seen.move_to_end(key)
                while len(self._seen) > self.max_entries:
                    self._seen.popitem(last=False)
        return principal

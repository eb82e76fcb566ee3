"""API tokens: roles ``viewer`` < ``operator`` < ``admin``; shown once, stored as SHA-256 hashes.

Tokens are random (256 bits), so a plain hash is enough; they are never logged.
"""

from __future__ import annotations

import hashlib
import secrets
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
    if not token:
        return None
    with sessions() as s:
        row = s.scalar(select(ApiToken).where(ApiToken.token_hash == hash_token(token), ApiToken.revoked.is_(False)))
        return Principal(row.name, row.role) if row else None

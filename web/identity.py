"""Who a console browser is, passed from the service's WebSocket proxy to the viser side.

viser does not know who a browser is, and any local process can reach its 127.0.0.1 port. The proxy
adds a header to each upstream handshake with the logged-in user's name and role, signed with a key
that exists only in the service process (HMAC-SHA256) and valid for a short time. The viser side
accepts a connection only with a valid signature, and attributes every console action to that user.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import time
from dataclasses import dataclass

from server.auth import ROLES

HEADER = "x-hitl-console-identity"
TTL_S = 30.0  # a signed identity is good for one handshake, made right after it is signed


@dataclass(frozen=True)
class Identity:
    name: str
    role: str

    def has(self, role: str) -> bool:
        return ROLES.index(self.role) >= ROLES.index(role)


class IdentitySigner:
    def __init__(self, key: bytes | None = None, ttl_s: float = TTL_S) -> None:
        self._key = key or secrets.token_bytes(32)
        self.ttl_s = ttl_s

    def _mac(self, payload: bytes) -> str:
        return base64.urlsafe_b64encode(hmac.new(self._key, payload, hashlib.sha256).digest()).decode()

    def sign(self, identity: Identity) -> str:
        body = {"name": identity.name, "role": identity.role, "exp": time.time() + self.ttl_s}
        payload = base64.urlsafe_b64encode(json.dumps(body, separators=(",", ":")).encode())
        return f"{payload.decode()}.{self._mac(payload)}"

    def verify(self, value: str | None) -> Identity | None:
        """The identity in a signed value, or None: missing, forged, expired or malformed."""
        if not value or value.count(".") != 1:
            return None
        payload, mac = value.split(".")
        try:  # header bytes that are not ASCII arrive as surrogates: compared and decoded as bytes, or refused
            raw = payload.encode("ascii")
            if not hmac.compare_digest(self._mac(raw).encode("ascii"), mac.encode("utf-8", "surrogateescape")):
                return None
            body = json.loads(base64.urlsafe_b64decode(raw))
            name, role, exp = str(body["name"]), str(body["role"]), float(body["exp"])
        except (ValueError, KeyError, TypeError, UnicodeError):
            return None
        if exp < time.time() or role not in ROLES:
            return None
        return Identity(name, role)

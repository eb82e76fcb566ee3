"""Dependencies: the services built in the lifespan, and token authentication by role.

``get_fleet`` and the role check are ``async``: they run on the event loop instead of costing a
threadpool hop per request, and the token check reads the lifespan's ``TokenCache`` (a database query,
in the threadpool, only on a miss: once per token per few seconds)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import sessionmaker

from server.auth import Principal, TokenCache, forbidden
from server.port import FleetPort

_bearer = HTTPBearer(auto_error=False)


async def get_fleet(request: Request) -> FleetPort:
    return request.app.state.fleet


def get_sessions(request: Request) -> sessionmaker:
    return request.app.state.sessions


FleetDep = Annotated[FleetPort, Depends(get_fleet)]


async def call_port(fleet: FleetPort, method, *args):
    """``method(*args)`` for a bound member of ``fleet``: at once when the runtime is in this process (the
    members the async routes call never wait for a tick), from the threadpool when the call crosses to a
    runtime in another process (``fleet.remote``), so the event loop never waits on its socket."""
    if fleet.remote:
        return await run_in_threadpool(method, *args)
    return method(*args)


SessionsDep = Annotated[sessionmaker, Depends(get_sessions)]


async def _lookup(cache: TokenCache, token: str | None) -> Principal | None:
    """The cached answer, or the database's, asked from the threadpool: never a query on the event loop."""
    known, principal = cache.cached(token)
    return principal if known else await run_in_threadpool(cache.authenticate, token)


async def lookup_principal(app, token: str | None) -> Principal | None:
    """The principal of an API token, through the app's token cache (the console's log-in uses it)."""
    return await _lookup(app.state.tokens, token)


async def lookup_token_hash(app, token_hash: str | None) -> Principal | None:
    """The principal of the API token with this hash (what a console session keeps), through the cache."""
    if not token_hash:
        return None
    known, principal = app.state.tokens.cached_hash(token_hash)
    return principal if known else await run_in_threadpool(app.state.tokens.authenticate_hash, token_hash)


async def _principal(request: Request, creds: HTTPAuthorizationCredentials | None) -> Principal:
    principal = await _lookup(request.app.state.tokens, creds.credentials if creds else None)
    if principal is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, "missing or invalid API token", headers={"WWW-Authenticate": "Bearer"}
        )
    return principal


def require(role: str):
    async def dependency(
        request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
    ) -> Principal:
        principal = await _principal(request, creds)
        if not principal.has(role):
            raise HTTPException(status.HTTP_403_FORBIDDEN, forbidden(role, principal.role))
        return principal

    dependency.role = role  # routes behind it answer 401 and 403 (server.api.responses.AUTH)
    return dependency


Viewer = Annotated[Principal, Depends(require("viewer"))]
Operator = Annotated[Principal, Depends(require("operator"))]
Admin = Annotated[Principal, Depends(require("admin"))]


async def websocket_principal(websocket: WebSocket, role: str) -> Principal | None:
    """Token from ``Authorization: Bearer`` or the ``token`` query parameter; None if not allowed."""
    header = websocket.headers.get("authorization", "")
    token = header.removeprefix("Bearer ").strip() if header.startswith("Bearer ") else None
    token = token or websocket.query_params.get("token")
    principal = await _lookup(websocket.app.state.tokens, token)
    return principal if principal is not None and principal.has(role) else None

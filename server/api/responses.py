"""The error answers each route documents: one schema (``ErrorOut``, what the ServiceError, HTTPException,
validation and body-limit answers all send) and one helper that builds a route's ``responses=``."""

from __future__ import annotations

from server.api.schemas import ErrorOut

AUTH = (401, 403)  # every route behind a token: none or an unknown one, or too weak a role
# every route with a body: not UTF-8 text (FastAPI answers 400 before JSON decoding), over max_body_bytes
# (server.app.BodyLimit), or invalid
BODY = (400, 413, 422)

_WHY = {
    400: "the body cannot be parsed: it is not UTF-8 text",
    401: "missing or invalid API token",
    403: "the token's role is not enough for this route",
    404: "no such robot, or no such record",
    409: "the request conflicts with the current state",
    410: "the record's file is gone from the data folder",
    413: "the body is larger than max_body_bytes",
    422: "the request does not validate: path, query or body",
    429: "too fast: the commands waiting for the next control tick would exceed the per-step limits",
}
_HEADERS = {401: {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}}}


def errors(*statuses: int | tuple[int, ...], why: dict[int, str] | None = None) -> dict[int | str, dict]:
    """``responses=`` for a route that can answer ``statuses`` (ints or groups such as ``AUTH``), each
    with ``ErrorOut``; ``why`` replaces the generic description of some of them."""
    flat = sorted({s for item in statuses for s in (item if isinstance(item, tuple) else (item,))})
    out: dict[int | str, dict] = {}
    for status in flat:
        entry = {"model": ErrorOut, "description": (why or {}).get(status, _WHY[status])}
        if status in _HEADERS:
            entry["headers"] = _HEADERS[status]
        out[status] = entry
    return out

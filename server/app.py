"""``create_app(settings)``: the FastAPI service. Nothing is created at import time.

The lifespan applies migrations, recovers takeover segments left open by a crash, builds the
fleet and starts its control loop; on shutdown (SIGTERM included, through uvicorn) it finishes
the current tick, closes open segments and stops the workers.
"""

from __future__ import annotations

import logging
import re
from contextlib import asynccontextmanager
from datetime import UTC, datetime

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy import select

from server.api import assistance, records, robots, system
from server.db import SegmentRecord, make_engine, migrate, session_factory
from server.errors import ServiceError
from server.fleet import Fleet
from server.settings import Settings
from storage.segments import SegmentReadError, read_segment

log = logging.getLogger("hitl.server")
API_PREFIX = "/api/v1"


class RedactTokens(logging.Filter):
    """Access logs never show a token passed as ``?token=``."""

    _pattern = re.compile(r"(token=)[^&\s\"]+")

    def filter(self, record: logging.LogRecord) -> bool:
        if record.args:
            record.args = tuple(self._pattern.sub(r"\1***", a) if isinstance(a, str) else a for a in record.args)
        record.msg = self._pattern.sub(r"\1***", str(record.msg))
        return True


class BodyLimit:
    """Rejects request bodies over ``max_bytes`` with 413, whether or not they declare their length
    (chunked bodies are read up to the limit, then replayed to the app)."""

    def __init__(self, app, max_bytes: int) -> None:
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        too_big = JSONResponse({"detail": f"body larger than {self.max_bytes} bytes"}, status_code=413)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None:
            if not length.isdigit() or int(length) > self.max_bytes:
                await too_big(scope, receive, send)
                return
            await self.app(scope, receive, send)
            return
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                break
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            more = message.get("more_body", False)
            if size > self.max_bytes:
                await too_big(scope, receive, send)
                return
        body, replayed = b"".join(chunks), False

        async def replay():
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def recover_segments(sessions) -> int:
    """Marks segments left open by a crash ``recovered``, with the steps their files still hold."""
    n = 0
    with sessions() as s:
        for row in s.scalars(select(SegmentRecord).where(SegmentRecord.status == "open")):
            try:
                seg = read_segment(row.path, recover=True)
                row.steps = len(seg.steps)
            except SegmentReadError as exc:
                log.warning("segment %d: %s", row.id, exc)
                row.steps = 0
            row.status, row.ended_at = "recovered", datetime.now(UTC)
            n += 1
        s.commit()
    return n


def create_app(settings: Settings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        url = settings.db_url
        migrate(url)
        engine = make_engine(url)
        sessions = session_factory(engine)
        recovered = recover_segments(sessions)
        if recovered:
            log.info("recovered %d takeover segment(s) left open by a crash", recovered)
        fleet = Fleet(settings, sessions)
        app.state.settings, app.state.sessions, app.state.fleet = settings, sessions, fleet
        fleet.start()
        try:
            yield
        finally:
            fleet.stop()
            engine.dispose()

    app = FastAPI(
        title="hitl fleet service",
        version="0.1.0",
        description="Robots ask for help when their denoising uncertainty is high; operators take over.",
        lifespan=lifespan,
    )

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse({"detail": exc.message}, status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        # the offending values are not echoed back: NaN and infinities are not JSON
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.include_router(system.router)
    for router in (robots.router, assistance.router, records.router, system.api):
        app.include_router(router, prefix=API_PREFIX)
    return app

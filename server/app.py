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

    @app.middleware("http")
    async def limit_body(request: Request, call_next):
        length = request.headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > settings.max_body_bytes):
            return JSONResponse({"detail": f"body larger than {settings.max_body_bytes} bytes"}, status_code=413)
        return await call_next(request)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        # the offending values are not echoed back: NaN and infinities are not JSON
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    app.include_router(system.router)
    for router in (robots.router, assistance.router, records.router, system.api):
        app.include_router(router, prefix=API_PREFIX)
    return app

"""``create_app(settings, extensions)``: the FastAPI service. Nothing is created at import time.

The service as run (``hitl serve``) is assembled one level up, in ``service.app``, which mounts the
operator console (``web/``) as an extension: this package never imports ``web/``.

The lifespan applies migrations, recovers the segments and episodes a crash left open, builds the
fleet and starts its control loop; on shutdown (SIGTERM included, through uvicorn) it finishes
the current tick, closes open segments and stops the workers.

Operations: ``/docs`` (Swagger UI) and ``/redoc`` are served with their assets from the installed
``fastapi-offline`` package (no CDN), ``/`` redirects to ``home_path()``, the OpenAPI document carries the
teleop WebSocket's message schemas (``server.api.ws_messages``), one ``ready: ...`` line is logged when
``/readyz`` turns ready, and the access log keeps successful polling GETs at debug level.
"""

from __future__ import annotations

import asyncio
import importlib.resources
import logging
import os
import re
from collections.abc import Sequence
from contextlib import asynccontextmanager
from typing import Protocol

from fastapi import APIRouter, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from server.api import assistance, finetune, policies, records, robots, system, ws_messages
from server.api.schemas import ErrorOut, FieldError
from server.auth import TokenCache
from server.db import make_engine, session_factory
from server.errors import ServiceError
from server.finetune.scheduler import JobLauncher, ScheduleStatus
from server.port import FleetPort
from server.runtime.client import RemoteFleet
from server.runtime.local import FleetRuntime
from server.runtime.wire import RuntimeLink
from server.settings import Settings

log = logging.getLogger("hitl.server")
API_PREFIX = "/api/v1"
HTTP_METHODS = frozenset({"get", "put", "post", "delete", "options", "head", "patch", "trace"})
DOCS_PATH = "/docs"
REDOC_PATH = "/redoc"
DOCS_ASSETS = "/docs/assets"  # Swagger UI's and ReDoc's files, from the fastapi-offline package
# The operator console's page: "/" and the ready line point to it (to the API docs when the console is off).
CONSOLE_PATH = "/console/"
DESCRIPTION = "Robots ask for help when their denoising uncertainty is high; operators take over."

# What clients poll: successful GETs of these go to the access log at debug level, the rest at info.
POLLED = re.compile(rf"^(/healthz|/readyz|/metrics|{API_PREFIX}/(robots(/\d+(/view)?)?|assistance|metrics/fleet))/?$")


def home_path(app: FastAPI | None = None) -> str:
    """Where ``/`` sends a browser: the console (``CONSOLE_PATH``), or the API docs when it is off."""
    settings = getattr(getattr(app, "state", None), "settings", None)
    return CONSOLE_PATH if settings is None or settings.console else DOCS_PATH


class RedactTokens(logging.Filter):
    """Access logs never show a token passed as ``?token=``."""

    _pattern = re.compile(r"(token=)[^&\s\"]+")

    def filter(self, record: logging.LogRecord) -> bool:
        if record.args:
            record.args = tuple(self._pattern.sub(r"\1***", a) if isinstance(a, str) else a for a in record.args)
        record.msg = self._pattern.sub(r"\1***", str(record.msg))
        return True


class QuietPolling(logging.Filter):
    """uvicorn's access-log line for a successful (< 400) GET of a polled endpoint (``POLLED``) becomes a
    debug record, dropped unless ``uvicorn.access`` logs at debug (``hitl serve --log-level debug``).
    Mutations and errors stay at info."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if not (isinstance(args, tuple) and len(args) == 5):  # client, method, path?query, version, status
            return True
        _, method, path, _, status = args
        if method not in ("GET", "HEAD") or not isinstance(status, int) or status >= 400:
            return True
        if not POLLED.match(str(path).split("?", 1)[0]):
            return True
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


def install_log_filters() -> None:
    """Token redaction on uvicorn's access log and on its error log (which logs each WebSocket handshake
    with its query string), and ``QuietPolling`` on the access log. Idempotent."""
    for name, kinds in (("uvicorn.access", (RedactTokens, QuietPolling)), ("uvicorn.error", (RedactTokens,))):
        logger = logging.getLogger(name)
        for kind in kinds:
            if not any(isinstance(f, kind) for f in logger.filters):
                logger.addFilter(kind())


def _replica_schedule(fleet: RemoteFleet, launcher: JobLauncher) -> ScheduleStatus:
    """An API replica's schedule: the runtime's (it runs the scheduler), with the jobs this replica started."""
    status = fleet.schedule_status() or ScheduleStatus.of(None, launcher)
    return status.with_launcher(launcher)


def allowed_methods(app: FastAPI, path: str, also: str = "") -> list[str]:
    """Every method the API documents at ``path`` (its OpenAPI document: a path served by several
    routes, as GET and POST ``/policies``, allows all of theirs; FastAPI serves no HEAD for a GET), with
    ``also``, the methods Starlette named (routes outside the document), sorted."""
    methods = {m.strip().upper() for m in also.split(",") if m.strip()}
    for template, operations in app.openapi().get("paths", {}).items():
        pattern = "^" + re.sub(r"\\{[^/]+?\\}", "[^/]+", re.escape(template)) + "/?$"
        if re.match(pattern, path):
            methods |= {m.upper() for m in operations if m.lower() in HTTP_METHODS}
    return sorted(methods)


def fleet_ready(fleet: FleetPort | None) -> bool:
    """What ``/readyz`` answers: the control loop has ticked (some robot's first frame arrived and was stepped)."""
    return fleet is not None and fleet.ticks > 0


def base_url(app: FastAPI) -> str:
    """The service's URL: the address uvicorn bound when ``hitl serve`` put its server in ``app.state.server``,
    else the settings'. A wildcard host (0.0.0.0, ::) is shown as this machine's loopback address."""
    settings = app.state.settings
    host, port = settings.host, settings.port
    server = getattr(app.state, "server", None)
    sockets = [sock for srv in getattr(server, "servers", None) or [] for sock in srv.sockets]
    if sockets:
        host, port = sockets[0].getsockname()[:2]
    host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(host, host)
    return f"http://{f'[{host}]' if ':' in host else host}:{port}"


def ready_line(app: FastAPI) -> str:
    base, n = base_url(app), len(app.state.fleet.views())
    console = f"console at {base}{CONSOLE_PATH}" if app.state.settings.console else "console off"
    return f"ready: {n} robot{'s' if n != 1 else ''}, {console}, docs at {base}{DOCS_PATH}"


async def announce_ready(app: FastAPI, poll_s: float = 0.05) -> None:
    """Logs ``ready_line`` once, when ``/readyz`` turns ready (and, under ``hitl serve``, uvicorn listens)."""
    server = getattr(app.state, "server", None)
    while not (fleet_ready(app.state.fleet) and (server is None or server.started)):
        await asyncio.sleep(poll_s)
    log.info("%s", ready_line(app))


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


class ServiceExtension(Protocol):
    """What a part of the service that lives above ``server/`` adds to the app (the operator console,
    ``web.extension``): routes, and what it runs beside the fleet. ``start`` is called once the fleet is
    built and before its control loop starts; ``stop`` on shutdown, before the fleet stops."""

    router: APIRouter

    def start(self, app: FastAPI, fleet: FleetPort) -> None: ...

    def stop(self, app: FastAPI) -> None: ...


def create_app(
    settings: Settings, extensions: Sequence[ServiceExtension] = (), link: RuntimeLink | None = None
) -> FastAPI:
    """The REST service on ``settings``, with ``extensions`` mounted (``service.app.create_app`` adds the
    console). ``link``: the fleet runtime runs in another process, reached there (an API replica,
    ``service.replicas``); None: this app runs the runtime (``server.runtime.local``)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        install_log_filters()
        app.state.settings = settings
        if link is None:  # the fleet runtime in this process
            runtime = FleetRuntime(settings).open()
            fleet, sessions, launcher = runtime.fleet, runtime.sessions, runtime.launcher
            app.state.schedule_status = runtime.schedule_status
        else:  # an API process of a runtime elsewhere (service.replicas)
            runtime = None
            engine = make_engine(settings.db_url)
            sessions = session_factory(engine)
            launcher = JobLauncher(settings.data_dir, settings.db_url, settings.finetune)  # jobs started here
            fleet = RemoteFleet(settings, link.address, link.authkey, sessions, who=f"api-{os.getpid()}")
            await run_in_threadpool(fleet.start)
            app.state.schedule_status = lambda: _replica_schedule(fleet, launcher)
        app.state.sessions, app.state.fleet, app.state.launcher = sessions, fleet, launcher
        app.state.tokens = TokenCache(sessions)
        for extension in extensions:
            extension.start(app, fleet)
        if runtime is not None:
            runtime.start()
        announcer = asyncio.create_task(announce_ready(app))
        try:
            yield
        finally:
            announcer.cancel()
            await asyncio.gather(announcer, return_exceptions=True)
            for extension in reversed(extensions):
                extension.stop(app)
            if runtime is not None:
                runtime.stop()
            else:
                launcher.stop()
                fleet.stop()
                engine.dispose()

    app = FastAPI(
        title="hitl fleet service",
        version="0.1.0",
        description=f"{DESCRIPTION}\n\n{ws_messages.PROTOCOL_MARKDOWN}",
        lifespan=lifespan,
        docs_url=None,  # served below, with local assets
        redoc_url=None,
    )

    # Every error answer has the documented ErrorOut shape (server.api.responses): these two, FastAPI's
    # HTTPException handler ({"detail": message}) and BodyLimit's 413 alike.
    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(ErrorOut(detail=exc.message).model_dump(), status_code=exc.status)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code != 405:
            return await http_exception_handler(request, exc)
        # Starlette names only the methods of the first route that matched the path; a path served by
        # several routes (GET and POST /policies) allows all of theirs (RFC 9110, 15.5.6)
        allow = ", ".join(allowed_methods(request.app, request.url.path, (exc.headers or {}).get("Allow", "")))
        return JSONResponse(ErrorOut(detail=str(exc.detail)).model_dump(), status_code=405, headers={"Allow": allow})

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        # the offending values are not echoed back: NaN and infinities are not JSON
        errors = [FieldError(loc=list(e["loc"]), msg=e["msg"], type=e["type"]) for e in exc.errors()]
        return JSONResponse(ErrorOut(detail=errors).model_dump(), status_code=422)

    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.include_router(system.router)
    for extension in extensions:
        app.include_router(extension.router)
    for router in (robots.router, assistance.router, records.router, policies.router, finetune.router, system.api):
        app.include_router(router, prefix=API_PREFIX)
    _add_docs(app)
    return app


def _add_docs(app: FastAPI) -> None:
    """``/`` (a redirect to ``home_path()``), ``/docs`` and ``/redoc`` with their assets served from the
    installed fastapi-offline package (FastAPI's documented self-hosting: docs_url=None, StaticFiles and
    ``get_swagger_ui_html``), and an OpenAPI document with the teleop WebSocket's message schemas."""
    assets = importlib.resources.files("fastapi_offline") / "static"
    app.mount(DOCS_ASSETS, StaticFiles(directory=str(assets)), name="docs-assets")

    def root(request: Request) -> str:
        return request.scope.get("root_path", "").rstrip("/")

    @app.get("/", include_in_schema=False)
    async def home(request: Request) -> RedirectResponse:
        return RedirectResponse(root(request) + home_path(app))

    @app.get(DOCS_PATH, include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        r = root(request)
        return get_swagger_ui_html(
            openapi_url=r + app.openapi_url,
            title=f"{app.title}: API docs",
            swagger_js_url=f"{r}{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{r}{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{r}{DOCS_ASSETS}/favicon.png",
            swagger_ui_parameters={"validatorUrl": None},  # Swagger UI's default sends the spec to an online validator
        )

    @app.get(REDOC_PATH, include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        r = root(request)
        return get_redoc_html(
            openapi_url=r + app.openapi_url,
            title=f"{app.title}: API reference",
            redoc_js_url=f"{r}{DOCS_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{r}{DOCS_ASSETS}/favicon.png",
            with_google_fonts=False,
        )

    def openapi() -> dict:
        if not app.openapi_schema:
            ws_messages.add_to_openapi(FastAPI.openapi(app))  # FastAPI caches the document it builds
        return app.openapi_schema

    app.openapi = openapi

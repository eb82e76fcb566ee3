"""The operator console as an extension of the service (``server.app.ServiceExtension``): its pages and
socket (``web.pages``), the browser sessions they share, and the ``Console`` that ticks beside the fleet
when the settings turn it on. ``service.app`` mounts it."""

from __future__ import annotations

from fastapi import FastAPI

from server.port import FleetPort
from web import pages
from web.console import Console
from web.sessions import ConsoleSessions, SharedConsoleSessions


class ConsoleExtension:
    """``app.state.console_sessions`` always (the log-in pages answer even with the console off; in the
    database when the API runs apart from the runtime) and
    ``app.state.console``: the running ``Console``, or None when ``settings.console`` is off."""

    router = pages.router

    def start(self, app: FastAPI, fleet: FleetPort) -> None:
        settings = app.state.settings
        # API processes apart from the runtime share log-ins through the database (web.sessions)
        app.state.console_sessions = SharedConsoleSessions(app.state.sessions) if fleet.remote else ConsoleSessions()
        app.state.console = None
        if settings.console:
            app.state.console = Console(fleet, settings.control_hz, sessions=app.state.sessions)
            app.state.console.start()

    def stop(self, app: FastAPI) -> None:
        if app.state.console is not None:
            app.state.console.stop()

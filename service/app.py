"""``create_app(settings)``: the app ``hitl serve`` runs, the benchmarks measure and the tests start.

The REST service of ``server.app`` with the operator console (``web.extension.ConsoleExtension``)
mounted. Nothing is created at import time: each call builds a new app, and its lifespan builds the
fleet and the console.
"""

from __future__ import annotations

from fastapi import FastAPI

from server.app import create_app as create_service
from server.runtime.wire import RuntimeLink
from server.settings import Settings
from web.extension import ConsoleExtension


def create_app(settings: Settings, link: RuntimeLink | None = None) -> FastAPI:
    """``link``: an API process of a fleet runtime that runs elsewhere (``service.replicas``)."""
    return create_service(settings, extensions=[ConsoleExtension()], link=link)

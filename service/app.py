"""``create_app(settings)``: the app ``hitl serve`` runs, the benchmarks measure and the tests start.

The REST service of ``server.app`` with the operator console (``web.extension.ConsoleExtension``)
mounted. Nothing is created at import time: each call builds a new app, and its lifespan builds the
fleet and the console.
"""

from __future__ import annotations

from fastapi import FastAPI

from server.app import create_app as create_service
from server.settings import Settings
from web.extension import ConsoleExtension


def create_app(settings: Settings) -> FastAPI:
    return create_service(settings, extensions=[ConsoleExtension()])

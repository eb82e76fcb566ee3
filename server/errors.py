"""The service's one domain error: every service method raises it, one exception handler maps it to
HTTP (``server.app``), and the WebSocket replies carry the same status."""

from __future__ import annotations


class ServiceError(Exception):
    """status: the HTTP status the API answers with (404 unknown, 409 conflict, 429 too fast, ...)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message

"""Every part of viser that the console relies on beyond its public API, named in one place.

viser is pinned exactly (``viser==1.1.1`` in pyproject.toml) because of these. When upgrading, check
each one against the new release.

- ``client_page()``: viser's browser client, one self-contained file shipped inside the package
  (``viser/client/build/index.html``). The page derives its WebSocket address from its own URL, so
  served at ``/console/`` it connects to ``/console``.
- ``CLIENT_QUERY_PARAMS``: query parameters the client page obeys. ``websocket`` makes it connect to
  another server and ``playbackPath`` makes it play a recording from any URL, so a crafted link
  could show an operator a fake console; the console refuses both.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

VISER_VERSION = "1.1.1"
CLIENT_QUERY_PARAMS = ("websocket", "playbackPath")


def client_page() -> Path:
    """The path of viser's single-file browser client (FileNotFoundError if the install lacks it)."""
    page = Path(str(importlib.resources.files("viser") / "client" / "build" / "index.html"))
    if not page.is_file():
        raise FileNotFoundError(f"viser's client page is missing from the install: {page}")
    return page

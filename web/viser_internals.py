"""Every part of viser (and mjviser) that the console relies on beyond the public API, named in one place.

viser and mjviser are pinned exactly (``viser==1.1.1``, ``mjviser==0.0.14`` in pyproject.toml) because
of these. When upgrading, check each one against the new release; ``tests/web`` exercises all of them.

- ``client_page()``: viser's browser client, one self-contained file shipped inside the package
  (``viser/client/build/index.html``). The page derives its WebSocket address from its own URL, so
  served at ``/console/`` it connects to ``/console``.
- ``CLIENT_QUERY_PARAMS``: query parameters the client page obeys. ``websocket`` makes it connect to
  another server and ``playbackPath`` makes it play a recording from any URL, so a crafted link
  could show an operator a fake console; the console refuses both.
- ``SUBPROTOCOL``: the client offers ``viser-v<version>`` and the server refuses any other version.
- ``SHARE_MESSAGES`` / ``remove_share_handlers``: the client can ask the server for a public share
  tunnel (``ShareUrlRequest``), and viser answers it whether or not the share button is shown. The
  console removes those handlers, and its proxy drops the messages (``message_type``).
- ``handshake_headers`` / ``close_client``: viser's ``ClientHandle`` does not expose the WebSocket
  handshake, which carries the signed identity the proxy adds, nor a way to close one connection.
- ``server_messages``: the frame viser's server sends a client (sizes, zstd-compressed msgpack, raw
  buffers), read by ``hitl bench console``'s protocol clients.
- ``quiet()``: viser prints a panel with its address when it starts and a line when it stops, whatever
  ``verbose`` says; the console logs its own line instead.
- ``move_fixed_body``: mjviser draws a body welded to the world (no joint) once, where the model put it
  when the scene was built; a task that places such a body per episode (the drawer's cabinet) moves
  its handles (``ViserMujocoScene._fixed_geom_handles``) instead of rebuilding the scene.
- ``hide_model_groups``: mjviser shows geom and site groups 0-2; robosuite puts its collision geoms in
  group 0, and its sites are helpers (the grip site's tall cylinder, object markers), not the scene.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.resources
import io
from pathlib import Path

import msgspec
import numpy as np
import viser
from viser import _messages

VISER_VERSION = "1.1.1"
if viser.__version__ != VISER_VERSION:  # the pin in pyproject.toml
    raise ImportError(f"the console needs viser {VISER_VERSION}, found {viser.__version__}: see web/viser_internals.py")
SUBPROTOCOL = f"viser-v{VISER_VERSION}"
CLIENT_QUERY_PARAMS = ("websocket", "playbackPath")
SHARE_MESSAGES = ("ShareUrlRequest", "ShareUrlDisconnect")
HIDDEN_GROUP = 3  # mjviser hides geom groups 3-5 by default


def client_page() -> Path:
    """The path of viser's single-file browser client (FileNotFoundError if the install lacks it)."""
    page = Path(str(importlib.resources.files("viser") / "client" / "build" / "index.html"))
    if not page.is_file():
        raise FileNotFoundError(f"viser's client page is missing from the install: {page}")
    return page


def message_type(raw: bytes) -> str | None:
    """The ``type`` of one client-to-server viser message (msgpack), or None if it is not one."""
    try:
        decoded = msgspec.msgpack.decode(raw)
    except (msgspec.DecodeError, ValueError, TypeError):
        return None
    kind = decoded.get("type") if isinstance(decoded, dict) else None
    return kind if isinstance(kind, str) else None


def remove_share_handlers(server: viser.ViserServer) -> None:
    """Unregisters the server's answers to share-tunnel requests: a crafted message opens no tunnel."""
    infra = server._websock_server
    for name in SHARE_MESSAGES:
        cls = getattr(_messages, name)
        if cls in infra._incoming_handlers:
            infra.unregister_handler(cls)


def share_handlers(server: viser.ViserServer) -> list[str]:
    """The share messages the server still answers (tests: empty after ``remove_share_handlers``)."""
    infra = server._websock_server
    return [name for name in SHARE_MESSAGES if getattr(_messages, name) in infra._incoming_handlers]


def handshake_headers(server: viser.ViserServer, client_id: int) -> dict[str, str]:
    """The HTTP headers of a connected client's WebSocket handshake (empty if it is gone)."""
    connection = server._websock_server._live_connections.get(client_id)
    if connection is None or connection.request is None:
        return {}
    return {k.lower(): v for k, v in connection.request.headers.raw_items()}


def close_client(server: viser.ViserServer, client_id: int, reason: str) -> None:
    """Closes one client's connection (policy violation, 1008), from any thread."""
    infra = server._websock_server
    connection = infra._live_connections.get(client_id)
    loop = infra._background_event_loop
    if connection is not None and loop is not None:
        asyncio.run_coroutine_threadsafe(connection.close(1008, reason[:120]), loop)


def hide_model_groups(model, groups: tuple[int, ...] = (0,)) -> None:
    """Moves the geoms of ``groups`` (robosuite's collision geoms: 0), the geoms of mocap bodies and every
    site to a group mjviser hides, in place: call it on the browser's own copy of the model. The mocap
    bodies are robosuite's end-effector target markers (``left_eef_target``, ``right_eef_target``: a
    translucent 10 cm box), parked at z = -1 m, which no frame moves: drawn, a cube floats under the table."""
    model.geom_group[np.isin(model.geom_group, groups)] = HIDDEN_GROUP
    model.geom_group[model.body_mocapid[model.geom_bodyid] >= 0] = HIDDEN_GROUP
    model.site_group[:] = HIDDEN_GROUP


def move_fixed_body(scene, body: int, position: np.ndarray, wxyz: np.ndarray) -> None:
    """Moves the geometry mjviser drew for ``body``, a body welded to the world, of ``scene``
    (``mjviser.ViserMujocoScene``) to the world pose (``position``, ``wxyz``)."""
    for (owner, _group, _sub), handle in scene._fixed_geom_handles.items():
        if owner == body:
            handle.position, handle.wxyz = position, wxyz


def server_messages(frame: bytes) -> list[dict]:
    """The messages of one frame viser's server sent a client: its decompressed and compressed sizes (8 bytes
    each, little-endian), the zstd-compressed msgpack ``{"messages": [...], ...}``, then raw buffers."""
    import zstandard  # viser's own dependency

    size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    window = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16 : 16 + packed], size))
    return list(window.get("messages", ())) if isinstance(window, dict) else []


def on_handshake(server: viser.ViserServer, callback, hangup) -> None:
    """``callback(client_id)`` right after a WebSocket handshake, before viser's own connect callbacks
    (which wait for the client's first camera message) and before the client is sent its state;
    ``hangup(client_id)`` when that connection ends, whether or not viser's own callbacks ran."""
    infra = server._websock_server
    infra.on_client_connect(lambda connection: callback(connection.client_id))
    infra.on_client_disconnect(lambda connection: hangup(connection.client_id))


def quiet():
    """Swallows what viser prints to stdout (its start panel, its stop line) while in the block."""
    return contextlib.redirect_stdout(io.StringIO())


def show_jpeg(handle: viser.GuiImageHandle, jpeg: bytes) -> None:
    """Shows JPEG bytes as they are in a GUI image (a camera view, encoded once by the renderer): viser's
    public ``image`` setter takes an array and encodes it again. Its props ``_format`` and ``_data`` are
    what that setter assigns and what viser 1.1.1 sends to the browser."""
    handle._format = "jpeg"
    handle._data = jpeg

"""The console's WebSocket proxy: a browser's viser connection, relayed to the internal viser server.

The service's route (``web.pages``) checks the session and the ``Origin`` first; ``relay``
then connects upstream with viser's subprotocol and the signed identity, accepts the browser with the
same subprotocol, and relays binary frames both ways until either side closes or ``alive`` says the
session has ended (log-out, revoked token), checked every ``check_s`` seconds.

- A text frame from the browser closes its socket (1003): viser speaks only binary msgpack.
- Share-tunnel messages (``viser_internals.SHARE_MESSAGES``) are dropped, never forwarded.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable

import websockets
from starlette.websockets import WebSocket, WebSocketDisconnect

from web.viser_internals import SHARE_MESSAGES, SUBPROTOCOL, message_type

log = logging.getLogger("hitl.console")

CHECK_S = 1.0  # how often a live socket re-checks its session
CLOSE_SESSION_ENDED = 1008  # policy violation: the session ended (log-out, revoked token)
CLOSE_TEXT_FRAME = 1003  # unsupported data


async def relay(
    browser: WebSocket,
    upstream_url: str,
    headers: dict[str, str],
    alive: Callable[[], Awaitable[bool]],
    check_s: float = CHECK_S,
) -> None:
    try:
        upstream = await websockets.connect(
            upstream_url,
            subprotocols=[SUBPROTOCOL],
            additional_headers=headers,
            max_size=None,
            compression=None,
            open_timeout=10,
        )
    except (OSError, websockets.WebSocketException, TimeoutError) as exc:
        log.warning("console: the viser server did not accept the connection: %s", exc)
        await browser.close(1011, "console unavailable")
        return
    try:
        await browser.accept(subprotocol=SUBPROTOCOL)
    except BaseException:
        await upstream.close()
        raise

    async def browser_to_upstream() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            if data is None:
                await browser.close(CLOSE_TEXT_FRAME, "binary frames only")
                return
            if message_type(data) in SHARE_MESSAGES:
                continue
            await upstream.send(data)

    async def upstream_to_browser() -> None:
        async for data in upstream:
            if isinstance(data, bytes):
                await browser.send_bytes(data)

    async def watch_session() -> None:
        while True:
            await asyncio.sleep(check_s)
            if not await alive():
                await browser.close(CLOSE_SESSION_ENDED, "session ended: log in again")
                return

    tasks = [asyncio.create_task(c) for c in (browser_to_upstream(), upstream_to_browser(), watch_session())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        results = await asyncio.gather(*tasks, return_exceptions=True)
        await upstream.close()
        for result in results:
            if isinstance(result, Exception) and not isinstance(
                result, WebSocketDisconnect | websockets.ConnectionClosed | RuntimeError
            ):
                log.warning("console relay ended with %r", result)
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):  # already closed
            await browser.close()

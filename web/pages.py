"""The operator console's pages: log-in with an API token, the viser client page at ``/console/``,
and log-out. Not part of the REST API (left out of the OpenAPI document).

- Without a live session the page answers 401 with the log-in form.
- The session is an HttpOnly, SameSite=Strict cookie scoped to ``/console`` (``web.sessions``); the
  token behind it is re-checked on every use, so a revoked token ends the session.
- Log-in and log-out refuse a foreign ``Origin`` (403): SameSite alone does not stop a page on another
  port of the same host.
- A link carrying the client's ``websocket`` or ``playbackPath`` parameter is redirected to the bare
  page, so a crafted link cannot point an operator's console at another server or a fake recording.
- The page's WebSocket (``/console``) is admitted only with a live session and a same-origin ``Origin``
  (403 otherwise, 401 without a session), and relayed to the internal viser server with the user's
  signed identity (``web.proxy``, ``web.identity``). Log-out and token revocation close it within seconds.
"""

from __future__ import annotations

import html
from urllib.parse import parse_qs

from fastapi import APIRouter, Request, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from starlette.requests import HTTPConnection

from server.api.deps import lookup_principal, lookup_token_hash
from web.proxy import relay
from web.sessions import COOKIE, COOKIE_PATH, MAX_AGE_S
from web.viser_internals import CLIENT_QUERY_PARAMS, SUBPROTOCOL, client_page

PAGE = COOKIE_PATH + "/"
LOGIN = COOKIE_PATH + "/login"
LOGOUT = COOKIE_PATH + "/logout"
# Referrer-Policy same-origin, not no-referrer: under no-referrer a browser sends ``Origin: null`` with the
# log-in form's POST, which ``same_origin`` (rightly) refuses
PAGE_HEADERS = {"Cache-Control": "no-store", "X-Frame-Options": "DENY", "Referrer-Policy": "same-origin"}

router = APIRouter(include_in_schema=False)


def same_origin(conn: HTTPConnection) -> bool:
    """True without an ``Origin`` header (not a browser) or with this server's own origin (a WebSocket's
    ``ws``/``wss`` scheme is its page's ``http``/``https``)."""
    origin = conn.headers.get("origin")
    scheme = {"ws": "http", "wss": "https"}.get(conn.url.scheme, conn.url.scheme)
    return origin is None or origin == f"{scheme}://{conn.headers.get('host', '')}"


async def session_principal(app, sid: str | None):
    """The principal behind a console session id, or None (no session, logged out, token revoked)."""
    return await lookup_token_hash(app, await run_in_threadpool(app.state.console_sessions.token_hash, sid))


async def console_principal(conn: HTTPConnection):
    """The principal of the request's console session, or None."""
    return await session_principal(conn.app, conn.cookies.get(COOKIE))


def _login_page(message: str = "", status_code: int = 200) -> HTMLResponse:
    note = f'<p role="alert">{html.escape(message)}</p>' if message else ""
    body = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>hitl console: log in</title>
<style>body{{font-family:sans-serif;max-width:26rem;margin:4rem auto}}input{{width:100%;padding:.4rem}}</style>
</head><body>
<h1>Operator console</h1>{note}
<form method="post" action="{LOGIN}">
<label for="token">API token (viewer, operator or admin)</label>
<input id="token" name="token" type="password" autocomplete="off" required autofocus>
<p><button type="submit">Log in</button></p>
</form></body></html>"""
    return HTMLResponse(body, status_code=status_code, headers=PAGE_HEADERS)


@router.get(COOKIE_PATH)
async def console_root() -> RedirectResponse:
    return RedirectResponse(PAGE, status.HTTP_307_TEMPORARY_REDIRECT)


@router.get(PAGE)
async def console_page(request: Request) -> Response:
    if any(p in request.query_params for p in CLIENT_QUERY_PARAMS):
        return RedirectResponse(PAGE, status.HTTP_303_SEE_OTHER)
    if await console_principal(request) is None:
        return _login_page("Log in to open the console.", status.HTTP_401_UNAUTHORIZED)
    return FileResponse(client_page(), media_type="text/html", headers=PAGE_HEADERS)


@router.get(LOGIN)
async def login_form() -> HTMLResponse:
    return _login_page()


@router.post(LOGIN)
async def login(request: Request) -> Response:
    if not same_origin(request):
        return _login_page("Log-in from another site was refused.", status.HTTP_403_FORBIDDEN)
    try:
        fields = parse_qs((await request.body()).decode("utf-8"), max_num_fields=4)
    except (UnicodeDecodeError, ValueError):
        fields = {}
    token = (fields.get("token") or [""])[0].strip()
    if await lookup_principal(request.app, token) is None:
        return _login_page("That token is not valid.", status.HTTP_401_UNAUTHORIZED)
    response = RedirectResponse(PAGE, status.HTTP_303_SEE_OTHER)
    response.set_cookie(
        COOKIE,
        await run_in_threadpool(request.app.state.console_sessions.open, token),
        max_age=int(MAX_AGE_S),
        path=COOKIE_PATH,
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )
    return response


@router.post(LOGOUT)
async def logout(request: Request) -> Response:
    if not same_origin(request):
        return _login_page("Log-out from another site was refused.", status.HTTP_403_FORBIDDEN)
    await run_in_threadpool(request.app.state.console_sessions.close, request.cookies.get(COOKIE))
    response = RedirectResponse(LOGIN, status.HTTP_303_SEE_OTHER)
    response.delete_cookie(COOKIE, path=COOKIE_PATH, httponly=True, samesite="strict")
    return response


@router.websocket(COOKIE_PATH)
async def console_socket(websocket: WebSocket) -> None:
    """The viser client's socket: 403 for a foreign ``Origin`` (checked first: a page on another port of
    this host gets the cookie too), 401 without a live session, 400 without viser's subprotocol; else
    relayed to the internal viser server until either side closes or the session ends."""
    console = getattr(websocket.app.state, "console", None)
    if not same_origin(websocket):
        await websocket.send_denial_response(JSONResponse({"detail": "foreign origin"}, status_code=403))
        return
    sid = websocket.cookies.get(COOKIE)
    principal = await session_principal(websocket.app, sid)
    if principal is None:
        await websocket.send_denial_response(JSONResponse({"detail": "log in at /console/login"}, status_code=401))
        return
    if SUBPROTOCOL not in websocket.scope.get("subprotocols", []):
        await websocket.send_denial_response(
            JSONResponse({"detail": f"the console speaks {SUBPROTOCOL}: reload the page"}, status_code=400)
        )
        return
    if console is None:
        await websocket.send_denial_response(JSONResponse({"detail": "the console is off"}, status_code=503))
        return

    async def alive() -> bool:
        return await session_principal(websocket.app, sid) is not None

    await relay(websocket, console.upstream_url, console.sign(principal.name, principal.role), alive)

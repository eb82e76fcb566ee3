"""The console's WebSocket proxy and its viser server, on a real uvicorn server on 127.0.0.1: every
refusal, the share tunnel, the signed identity, and sockets closed by log-out and revocation."""

import time

import httpx
import msgspec
import pytest
import websockets
from websockets.sync.client import connect

from server.auth import create_token, revoke_token
from server.db import make_engine, migrate, session_factory
from server.errors import ServiceError
from server.settings import RobotGroup, Settings
from tests.helpers import Service, free_port, tiny_policy_folder
from web.actions import ConsoleActions
from web.identity import HEADER, Identity, IdentitySigner
from web.sessions import COOKIE
from web.viser_internals import SUBPROTOCOL, share_handlers


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("console-socket")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=1e9)
    settings = Settings(
        data_dir=root / "var", port=free_port(), robots=[RobotGroup(task="lift-cube", count=1, policy=policy)]
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    names = ("viewer", "operator", "revoked", "logout")
    roles = {"viewer": "viewer", "operator": "operator", "revoked": "operator", "logout": "operator"}
    tokens = {n: create_token(sessions, f"{n}-socket", roles[n]) for n in names}
    with Service(settings) as svc:
        svc.tokens, svc.sessions = tokens, sessions
        svc.ws = svc.url.replace("http://", "ws://") + "/console"
        yield svc


def _session(svc, name):
    answer = httpx.post(
        f"{svc.url}/console/login",
        content=f"token={svc.tokens[name]}",
        headers={"Content-Type": "application/x-www-form-urlencoded", "Origin": svc.url},
    )
    assert answer.status_code == 303
    return answer.cookies[COOKIE]


def _open(svc, sid=None, origin=None, subprotocols=(SUBPROTOCOL,)):
    headers = {"Origin": origin or svc.url}
    if sid:
        headers["Cookie"] = f"{COOKIE}={sid}"
    return connect(svc.ws, additional_headers=headers, subprotocols=list(subprotocols), open_timeout=10)


def _status(exc_info) -> int:
    return exc_info.value.response.status_code


def test_the_socket_needs_a_session_the_own_origin_and_viser_s_subprotocol(service):
    with pytest.raises(websockets.InvalidStatus) as no_session:
        _open(service)
    assert _status(no_session) == 401
    sid = _session(service, "operator")
    with pytest.raises(websockets.InvalidStatus) as forged:
        _open(service, "forged-session")
    assert _status(forged) == 401
    foreign = service.url.rsplit(":", 1)[0] + ":1"  # another port of this host: it gets the cookie too
    with pytest.raises(websockets.InvalidStatus) as other_origin:
        _open(service, sid, origin=foreign)
    assert _status(other_origin) == 403
    with pytest.raises(websockets.InvalidStatus) as null_origin:
        _open(service, sid, origin="null")
    assert _status(null_origin) == 403
    with pytest.raises(websockets.InvalidStatus) as wrong_version:
        _open(service, sid, subprotocols=("viser-v0.0.1",))
    assert _status(wrong_version) == 400

    with _open(service, sid) as ws:  # admitted: viser's state arrives, binary
        assert ws.subprotocol == SUBPROTOCOL
        assert isinstance(ws.recv(timeout=15), bytes)


def test_a_text_frame_closes_the_socket(service):
    with _open(service, _session(service, "operator")) as ws:
        ws.recv(timeout=15)
        ws.send("hello")
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=10)
        assert closed.value.rcvd.code == 1003


def test_a_crafted_share_request_opens_no_tunnel(service):
    console = service.app_state().console
    assert share_handlers(console.server) == []  # the server no longer answers it...
    with _open(service, _session(service, "operator")) as ws:
        ws.recv(timeout=15)
        for kind in ("ShareUrlRequest", "ShareUrlDisconnect"):
            ws.send(msgspec.msgpack.encode({"type": kind}))
        time.sleep(1.0)
        assert console.server._share_tunnel is None  # ...and the proxy drops it anyway
        assert ws.ping().wait(10)  # the socket stays open
    # straight to the internal port with a valid signature: still no tunnel
    headers = console.sign("operator-socket", "operator")
    with connect(console.upstream_url, additional_headers=headers, subprotocols=[SUBPROTOCOL]) as direct:
        direct.send(msgspec.msgpack.encode({"type": "ShareUrlRequest"}))
        time.sleep(1.0)
    assert console.server._share_tunnel is None


def test_the_internal_port_closes_connections_without_a_valid_signed_identity(service):
    console = service.app_state().console
    forged = IdentitySigner().sign(Identity("mallory", "admin"))  # another key
    for headers in ({}, {HEADER: forged}, {HEADER: "x.y"}):
        with connect(console.upstream_url, additional_headers=headers, subprotocols=[SUBPROTOCOL]) as ws:
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    ws.recv(timeout=10)
            assert closed.value.rcvd.code == 1008


def test_log_out_and_revocation_close_live_sockets_within_seconds(service):
    sid = _session(service, "logout")
    with _open(service, sid) as ws:
        ws.recv(timeout=15)
        httpx.post(f"{service.url}/console/logout", cookies={COOKIE: sid}, headers={"Origin": service.url})
        started = time.monotonic()
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=10)
        assert closed.value.rcvd.code == 1008 and time.monotonic() - started < 3.0
    sid = _session(service, "revoked")
    with _open(service, sid) as ws:
        ws.recv(timeout=15)
        assert revoke_token(service.sessions, "revoked-socket")
        started = time.monotonic()
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=15)
        # the token cache answers for up to 5 s, then the next check (every 1 s) sees the revocation
        assert closed.value.rcvd.code == 1008 and time.monotonic() - started < 8.0
    with pytest.raises(websockets.InvalidStatus) as again:
        _open(service, sid)
    assert _status(again) == 401


def test_a_viewer_cannot_claim_or_command(service):
    fleet = service.app_state().fleet
    viewer = ConsoleActions(fleet, Identity("viewer-socket", "viewer"))
    for attempt in (
        lambda: viewer.claim(0),
        lambda: viewer.command(0, [0.01, 0, 0], [0, 0, 0], -1.0),
        lambda: viewer.release(0),
        lambda: viewer.heartbeat(0),
    ):
        with pytest.raises(ServiceError) as refused:
            attempt()
        assert refused.value.status == 403 and "operator role" in refused.value.message
    operator = ConsoleActions(fleet, Identity("operator-socket", "operator"))
    with pytest.raises(ServiceError) as invalid:  # the API's body model: per-step limits
        operator.command(0, [0.5, 0, 0], [0, 0, 0], -1.0)
    assert invalid.value.status == 422
    with pytest.raises(ServiceError) as not_teleop:  # the fleet's own checks: not under teleop
        operator.command(0, [0.01, 0, 0], [0, 0, 0], -1.0)
    assert not_teleop.value.status == 409

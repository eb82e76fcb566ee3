"""The console's log-in, page and refusals, on a real uvicorn server on 127.0.0.1."""

import httpx
import pytest

from server.auth import create_token, revoke_token
from server.db import make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for
from web.sessions import COOKIE
from web.viser_internals import client_page


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("console")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=1e9)
    settings = Settings(
        data_dir=root / "var", port=free_port(), robots=[RobotGroup(task="lift-cube", count=1, policy=policy)]
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator")}
    with Service(settings) as svc:
        svc.tokens, svc.sessions = tokens, sessions
        yield svc


def _login(svc, token, origin=None):
    headers = {"Content-Type": "application/x-www-form-urlencoded"}
    if origin:
        headers["Origin"] = origin
    return httpx.post(f"{svc.url}/console/login", content=f"token={token}", headers=headers)


def test_the_page_needs_a_session_and_log_in_sets_a_strict_http_only_cookie(service):
    page = f"{service.url}/console/"
    bare = httpx.get(page)
    assert bare.status_code == 401 and 'name="token"' in bare.text  # the log-in form, not the console
    assert httpx.get(f"{service.url}/console").headers["location"] == "/console/"

    assert _login(service, "not-a-token").status_code == 401
    ok = _login(service, service.tokens["viewer"], origin=service.url)
    assert ok.status_code == 303 and ok.headers["location"] == "/console/"
    cookie = ok.headers["set-cookie"].lower()
    assert "httponly" in cookie and "samesite=strict" in cookie and "path=/console" in cookie
    assert service.tokens["viewer"] not in ok.headers["set-cookie"]  # the token stays on the server

    sid = ok.cookies[COOKIE]
    served = httpx.get(page, cookies={COOKIE: sid})
    assert served.status_code == 200 and served.text == client_page().read_text()
    assert served.headers["x-frame-options"] == "DENY" and served.headers["cache-control"] == "no-store"
    assert httpx.get(page, cookies={COOKIE: "forged"}).status_code == 401


def test_foreign_origins_and_crafted_links_are_refused(service):
    # a page on another port of the same host receives SameSite cookies; its Origin gives it away
    foreign = service.url.rsplit(":", 1)[0] + ":1"
    assert _login(service, service.tokens["operator"], origin=foreign).status_code == 403
    sid = _login(service, service.tokens["operator"]).cookies[COOKIE]
    for query in ("websocket=ws://127.0.0.1:1/evil", "playbackPath=http://127.0.0.1:1/fake.viser"):
        r = httpx.get(f"{service.url}/console/?{query}", cookies={COOKIE: sid})
        assert r.status_code == 303 and r.headers["location"] == "/console/"
    assert (
        httpx.post(f"{service.url}/console/logout", cookies={COOKIE: sid}, headers={"Origin": foreign}).status_code
        == 403
    )
    assert httpx.get(f"{service.url}/console/", cookies={COOKIE: sid}).status_code == 200  # still logged in


def test_log_out_and_revocation_end_the_session(service):
    sid = _login(service, service.tokens["operator"]).cookies[COOKIE]
    out = httpx.post(f"{service.url}/console/logout", cookies={COOKIE: sid})
    assert out.status_code == 303 and out.headers["location"] == "/console/login"
    assert httpx.get(f"{service.url}/console/", cookies={COOKIE: sid}).status_code == 401

    token = create_token(service.sessions, "viewer-2", "viewer")
    sid = _login(service, token).cookies[COOKIE]
    assert httpx.get(f"{service.url}/console/", cookies={COOKIE: sid}).status_code == 200
    assert revoke_token(service.sessions, "viewer-2")
    # the token cache forgets within its ttl (5 s): then the session is refused
    wait_for(lambda: httpx.get(f"{service.url}/console/", cookies={COOKIE: sid}).status_code == 401, timeout=15)

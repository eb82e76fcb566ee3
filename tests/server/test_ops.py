"""The service's operations surface, through the real ``hitl serve`` command on 127.0.0.1 (one in-process
robot, a tiny policy) and its log output: the ready line, offline /docs, the / redirect, the OpenAPI
message schemas of the teleop WebSocket and a real socket session validated against them, and the
access log (polling at debug, mutations and errors at info, tokens redacted)."""

import asyncio
import json
import logging
import math
import os
import re
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
from fastapi import FastAPI
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from server.api import ws_messages
from server.app import QuietPolling, announce_ready, install_log_filters
from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.settings import Settings
from tests.helpers import free_port, stop_process, tiny_policy_folder, wait_for

SERVER_MESSAGES = ("TeleopStateMessage", "TeleopAcceptedMessage", "TeleopErrorMessage")


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("ops")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=-1.0)  # the robot asks at once
    port = free_port()
    config = root / "ops.toml"
    config.write_text(
        f'data_dir = "{root / "var"}"\nhost = "127.0.0.1"\nport = {port}\ncontrol_hz = 20\n'
        '[workers]\nkind = "in-process"\n[controller]\nbudget = 1000\n[queue]\nlease_seconds = 120\n'
        "[inference]\ntrace_policies = false\n\n"
        f'[[robots]]\ntask = "lift-cube"\ncount = 1\npolicy = "{policy}"\n'
    )
    settings = Settings.load(config)
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator", "admin")}
    env = {k: v for k, v in os.environ.items() if not k.startswith("HITL_") and k != "DATABASE_URL"}
    log_path = root / "serve.log"
    hitl = Path(sys.executable).with_name("hitl")
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(
            [str(hitl), "serve", "--config", str(config)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env | {"PYTHONUNBUFFERED": "1"},
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 180
        while True:
            assert proc.poll() is None, f"hitl serve exited:\n{log_path.read_text()}"
            assert time.time() < deadline, f"not ready in time:\n{log_path.read_text()}"
            try:
                if httpx.get(url + "/readyz").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        yield SimpleNamespace(url=url, ws=url.replace("http", "ws"), tokens=tokens, log=log_path, policy=policy)
    finally:
        stop_process(proc)


def _h(svc, role):
    return {"Authorization": f"Bearer {svc.tokens[role]}"}


def _log(svc) -> str:
    return svc.log.read_text()


# -- a JSON-schema check for the keywords pydantic emits (an unknown keyword fails the test) -----------------
_ANNOTATIONS = {"title", "description", "default", "examples", "format", "deprecated"}
_CHECKED = {"$ref", "anyOf", "oneOf", "allOf", "const", "enum", "type", "properties", "required"}
_CHECKED |= {"additionalProperties", "items", "minItems", "maxItems", "minimum", "maximum"}
_CHECKED |= {"exclusiveMinimum", "exclusiveMaximum"}


def _is_type(value, kind: str) -> bool:
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return {
        "object": isinstance(value, dict),
        "array": isinstance(value, list),
        "string": isinstance(value, str),
        "boolean": isinstance(value, bool),
        "null": value is None,
        "number": number,
        "integer": number and float(value).is_integer(),
    }[kind]


def _valid(value, schema: dict, defs: dict) -> bool:
    unknown = set(schema) - _ANNOTATIONS - _CHECKED
    assert not unknown, f"extend the test's schema check for {unknown}"
    if "$ref" in schema:
        name = schema["$ref"].removeprefix("#/components/schemas/")
        return _valid(value, defs[name], defs)
    checks = [
        lambda: all(_valid(value, s, defs) for s in schema.get("allOf", [])),
        lambda: "anyOf" not in schema or any(_valid(value, s, defs) for s in schema["anyOf"]),
        lambda: "oneOf" not in schema or sum(_valid(value, s, defs) for s in schema["oneOf"]) == 1,
        lambda: "const" not in schema or value == schema["const"],
        lambda: "enum" not in schema or value in schema["enum"],
        lambda: (
            "type" not in schema
            or any(
                _is_type(value, t) for t in ([schema["type"]] if isinstance(schema["type"], str) else schema["type"])
            )
        ),
    ]
    if not all(check() for check in checks):
        return False
    if _is_type(value, "number"):
        bounds = [("minimum", value.__ge__), ("maximum", value.__le__)]
        bounds += [("exclusiveMinimum", value.__gt__), ("exclusiveMaximum", value.__lt__)]
        if not all(key not in schema or ok(schema[key]) for key, ok in bounds):
            return False
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0) or len(value) > schema.get("maxItems", math.inf):
            return False
        if "items" in schema and not all(_valid(v, schema["items"], defs) for v in value):
            return False
    if isinstance(value, dict):
        props = schema.get("properties", {})
        if not set(schema.get("required", [])) <= set(value):
            return False
        extra = schema.get("additionalProperties", True)
        for key, v in value.items():
            if key in props:
                if not _valid(v, props[key], defs):
                    return False
            elif extra is False or (isinstance(extra, dict) and not _valid(v, extra, defs)):
                return False
    return True


def _server_message(msg: dict, defs: dict) -> str:
    """The one server message type ``msg`` validates against, by the published schemas and by the models."""
    assert _valid(msg, defs["TeleopServerMessage"], defs), msg
    kinds = [name for name in SERVER_MESSAGES if _valid(msg, defs[name], defs)]
    assert len(kinds) == 1, (kinds, msg)
    assert type(ws_messages.TeleopServerMessage.model_validate(msg).root).__name__ == kinds[0]
    return kinds[0]


class _Assets(HTMLParser):
    def __init__(self):
        super().__init__()
        self.urls = []

    def handle_starttag(self, tag, attrs):
        self.urls += [v for k, v in attrs if k in ("src", "href") and v]


# -- tests ----------------------------------------------------------------------------------------------------
def test_the_ready_line_comes_when_the_service_is_ready(service):
    line = wait_for(lambda: re.search(r"^.*ready: .*$", _log(service), re.M), timeout=10).group(0)
    assert f"ready: 1 robot, console at {service.url}/console/, docs at {service.url}/docs" in line, line
    text = _log(service)
    assert text.count("ready: 1 robot") == 1
    # after the fleet started and after uvicorn listens (the first tick of an in-process robot comes sooner)
    assert text.index("fleet of 1 robot(s) started") < text.index("Uvicorn running on") < text.index("ready: ")
    assert httpx.get(service.url + "/readyz").json() == {"ready": True}


def test_ready_is_announced_when_the_fleet_has_ticked_and_the_server_listens(caplog):
    app = FastAPI()
    app.state.settings = SimpleNamespace(host="0.0.0.0", port=8123, console=False)
    app.state.fleet = SimpleNamespace(ticks=0, views=lambda: [None, None])  # the port's members it reads
    app.state.server = SimpleNamespace(started=False, servers=[])

    async def scenario():
        task = asyncio.create_task(announce_ready(app, poll_s=0.01))
        await asyncio.sleep(0.1)
        app.state.fleet.ticks = 1  # /readyz's condition, but uvicorn does not listen yet
        await asyncio.sleep(0.1)
        silent = not task.done()
        app.state.server.started = True
        await asyncio.wait_for(task, 2)
        return silent

    with caplog.at_level(logging.INFO, logger="hitl.server"):
        assert asyncio.run(scenario())
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("ready:")]
    assert lines == ["ready: 2 robots, console off, docs at http://127.0.0.1:8123/docs"]


def test_docs_are_served_offline_and_the_root_points_to_the_console(service):
    home = httpx.get(service.url + "/", follow_redirects=False)
    assert home.is_redirect and home.headers["location"] == "/console/"
    for page, needed in (("/docs", "swagger-ui-bundle.js"), ("/redoc", "redoc.standalone.js")):
        html = httpx.get(service.url + page)
        assert html.status_code == 200 and "text/html" in html.headers["content-type"]
        assert "http://" not in html.text and "https://" not in html.text and "//" not in html.text.replace("://", "")
        parser = _Assets()
        parser.feed(html.text)
        spec = re.findall(r"""(?:url: *'|spec-url=")([^'"]+)""", html.text)
        assert spec == ["/openapi.json"]
        urls = parser.urls + spec
        assert any(u.endswith(needed) for u in urls) and all(u.startswith("/") for u in urls), urls
        for u in urls:
            r = httpx.get(service.url + u)
            assert r.status_code == 200 and len(r.content) > 100, u
    js = httpx.get(service.url + "/docs/assets/swagger-ui-bundle.js")
    assert "javascript" in js.headers["content-type"] and "SwaggerUIBundle" in js.text
    assert '"validatorUrl": null' in httpx.get(service.url + "/docs").text  # no online spec validator


def test_the_openapi_document_has_the_websocket_message_schemas(service):
    doc = httpx.get(service.url + "/openapi.json").json()
    defs = doc["components"]["schemas"]
    names = ["TeleopCommandIn", *SERVER_MESSAGES, "TeleopServerMessage", "TeleopErrorItem"]
    assert all(name in defs for name in names)
    for name in names[:-1]:  # the messages (TeleopErrorItem is a part of TeleopErrorMessage)
        assert f"`{name}`" in doc["info"]["description"], name
    assert ws_messages.PATH in doc["info"]["description"]
    assert defs["TeleopAcceptedMessage"]["properties"]["accepted"]["const"] is True
    assert defs["TeleopStateMessage"]["properties"]["state"] == {"$ref": "#/components/schemas/RobotDetail"}
    # the published schemas are the models' own, and shared ones (RobotDetail, ...) equal the REST routes'
    assert all(defs[k] == v for k, v in ws_messages.json_schemas().items())

    def refs(node):
        if isinstance(node, dict):
            yield from ([node["$ref"]] if "$ref" in node else [])
            for v in node.values():
                yield from refs(v)
        elif isinstance(node, list):
            for v in node:
                yield from refs(v)

    assert all(r.removeprefix("#/components/schemas/") in defs for r in refs(doc))
    # the check below can fail: a message of no type, and one with a field too many
    assert not _valid({"accepted": True}, defs["TeleopServerMessage"], defs)
    assert not _valid({"accepted": True, "pending": 1, "x": 0}, defs["TeleopAcceptedMessage"], defs)


def _robot(svc, rid=0):
    return httpx.get(f"{svc.url}/api/v1/robots/{rid}", headers=_h(svc, "viewer")).json()


def test_a_teleop_socket_session_exchanges_messages_of_the_published_schemas(service):
    defs = httpx.get(service.url + "/openapi.json").json()["components"]["schemas"]
    if _robot(service)["mode"] != "teleop":
        wait_for(lambda: _robot(service)["mode"] == "waiting")
        claim = httpx.post(service.url + "/api/v1/robots/0/claim", headers=_h(service, "operator"))
        assert claim.status_code == 200, claim.text
    before = _robot(service)["assisted_steps"]
    good = {"delta_pos": [0.0, 0.0, 0.004], "gripper": -1.0}
    assert _valid(good, defs["TeleopCommandIn"], defs)
    sent = [
        json.dumps(good),
        "not json SECRET-VALUE",
        json.dumps({"delta_pos": [float("nan"), 0, 0], "gripper": -1}),
        json.dumps(good | {"speed": 3}),
        "[1, 2]",
        json.dumps(good | {"pad": "x" * 70_000}),  # over max_body_bytes (64 KiB)
        json.dumps(good).encode(),  # a binary frame
        json.dumps(good),
    ]
    expected = [
        ("TeleopAcceptedMessage", None),
        ("TeleopErrorMessage", 422, "json_invalid"),
        ("TeleopErrorMessage", 422, "NaN"),
        ("TeleopErrorMessage", 422, "extra_forbidden"),
        ("TeleopErrorMessage", 422, "model_type"),
        ("TeleopErrorMessage", 413, "larger than 65536 bytes"),
        ("TeleopAcceptedMessage", None),
        ("TeleopAcceptedMessage", None),
    ]
    answers, states = [], 0
    with connect(service.ws + "/api/v1/robots/0/teleop", additional_headers=_h(service, "operator")) as conn:
        for message in sent:
            conn.send(message)
        while len(answers) < len(sent) or states < 3:  # the state stream goes on after the refused messages
            msg = json.loads(conn.recv(timeout=10))
            if _server_message(msg, defs) == "TeleopStateMessage":
                states += 1 if answers else 0
                assert msg["state"]["id"] == 0
            else:
                answers.append(msg)
    for msg, (kind, status, *text) in zip(answers, expected, strict=True):
        assert _server_message(msg, defs) == kind, msg
        if kind == "TeleopAcceptedMessage":
            assert msg["accepted"] is True and msg["pending"] >= 1
        else:
            assert msg["status"] == status and text[0] in json.dumps(msg["error"]), msg
    assert "SECRET-VALUE" not in json.dumps(answers)  # bad input is never echoed
    # nothing was lost: the accepted commands were applied, and the robot is still under teleop
    wait_for(lambda: _robot(service)["assisted_steps"] > before, timeout=10)
    assert _robot(service)["mode"] == "teleop"

    # a viewer (?token=) watches but may not command
    with connect(f"{service.ws}/api/v1/robots/0/teleop?token={service.tokens['viewer']}") as conn:
        assert _server_message(json.loads(conn.recv(timeout=10)), defs) == "TeleopStateMessage"
        conn.send(json.dumps(good))
        replies = [json.loads(conn.recv(timeout=10)) for _ in range(4)]
        errors = [r for r in replies if _server_message(r, defs) == "TeleopErrorMessage"]
        assert errors and errors[0] == {"error": "commanding needs the operator role", "status": 403}
    # an unknown robot: one 404 error message, then the close code 4404
    with connect(service.ws + "/api/v1/robots/99/teleop", additional_headers=_h(service, "viewer")) as conn:
        msg = json.loads(conn.recv(timeout=10))
        assert _server_message(msg, defs) == "TeleopErrorMessage" and msg == {"error": "no robot 99", "status": 404}
        with pytest.raises(ConnectionClosed) as closed:
            conn.recv(timeout=10)
        assert closed.value.rcvd.code == ws_messages.CLOSE_UNKNOWN_ROBOT
    with pytest.raises(InvalidStatus) as denied:
        connect(service.ws + "/api/v1/robots/0/teleop")
    assert denied.value.response.status_code == 401


def test_polling_is_logged_at_debug_and_mutations_errors_at_info_without_tokens(service):
    api, viewer = service.url + "/api/v1", _h(service, "viewer")
    polled = ["/api/v1/robots", "/api/v1/robots/0", "/api/v1/robots/0/view", "/api/v1/assistance"]
    polled += ["/api/v1/metrics/fleet", "/metrics", "/healthz", "/readyz"]
    for path in polled:
        r = httpx.get(f"{service.url}{path}?probe=polled", headers=viewer)
        assert r.status_code == 200, (path, r.text)
    assert httpx.get(api + "/robots/99?probe=missing", headers=viewer).status_code == 404
    assert httpx.get(api + "/robots?probe=anonymous").status_code == 401
    r = httpx.post(api + "/policies?probe=mutation", json={"path": str(service.policy)}, headers=_h(service, "admin"))
    assert r.status_code < 400, r.text
    with connect(f"{service.ws}/api/v1/robots/0/teleop?token={service.tokens['viewer']}") as conn:
        conn.recv(timeout=10)
    with pytest.raises(InvalidStatus):
        connect(service.ws + "/api/v1/robots/0/teleop?token=not-a-token-SECRET")

    def logged():
        text = _log(service)
        return text if re.search(r'"WebSocket /api/v1/robots/0/teleop\?token=\*\*\*" 401', text) else None

    text = wait_for(logged, timeout=10)
    assert "?probe=polled" not in text
    assert re.search(r'INFO uvicorn.access: .*"GET /api/v1/robots/99\?probe=missing HTTP/1.1" 404', text)
    assert re.search(r'INFO uvicorn.access: .*"GET /api/v1/robots\?probe=anonymous HTTP/1.1" 401', text)
    assert re.search(r'INFO uvicorn.access: .*"POST /api/v1/policies\?probe=mutation HTTP/1.1" 2\d\d', text)
    assert re.search(r'INFO uvicorn.error: .*"WebSocket /api/v1/robots/0/teleop\?token=\*\*\*" \[accepted\]', text)
    assert re.search(r'INFO uvicorn.error: .*"WebSocket /api/v1/robots/0/teleop\?token=\*\*\*" 401', text)
    for token in (*service.tokens.values(), "not-a-token-SECRET"):
        assert token not in text


def test_polling_lines_show_at_debug_level():
    install_log_filters()
    access = logging.getLogger("uvicorn.access")
    assert any(isinstance(f, QuietPolling) for f in access.filters)
    level = access.level

    def passes(method, path, status):
        record = access.makeRecord(
            access.name, logging.INFO, __file__, 0, '%s - "%s %s HTTP/%s" %d', ("c", method, path, "1.1", status), None
        )
        kept = access.filter(record)
        return kept, record.levelname

    try:
        access.setLevel(logging.INFO)
        assert passes("GET", "/api/v1/robots/3/view?token=x", 200) == (False, "DEBUG")
        assert passes("GET", "/api/v1/robots/3/view", 404) == (True, "INFO")
        assert passes("POST", "/api/v1/robots/3/claim", 200) == (True, "INFO")
        assert passes("GET", "/api/v1/segments", 200) == (True, "INFO")  # not a polled endpoint
        access.setLevel(logging.DEBUG)
        assert passes("GET", "/readyz", 200) == (True, "DEBUG")
    finally:
        access.setLevel(level)

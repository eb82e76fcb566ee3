"""The HTTP API's contract, on a real uvicorn on 127.0.0.1 (in-process workers, one lift-cube robot that never
asks for help): ids out of the database's range, the statuses each route documents against those it can
answer, one error shape, /metrics as text, fixed vector lengths, and 409 (not 404) for a robot that exists."""

import json

import httpx
import pytest
from fastapi.routing import APIRoute

from server.api import assistance, finetune, policies, records, robots, system
from server.api.schemas import ID_MAX, ErrorOut
from server.app import API_PREFIX
from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from tests.helpers import Service, free_port, tiny_policy_folder

OUT_OF_RANGE = (2**31, 2**63, 10**30, -1, -(2**63) - 1)  # past what every supported database stores, or negative
UNKNOWN = ID_MAX  # in range, and names nothing
JSON = {"content-type": "application/json"}
COMMAND = {"delta_pos": [0.0, 0.0, 0.01], "delta_rot": [0.0, 0.0, 0.0], "gripper": -1.0}

# What each route's own code raises, beyond what its dependencies and parameters imply (see expected_errors).
RAISES = {
    ("GET", "/readyz"): {503},
    ("POST", "/api/v1/robots/{robot_id}/pause"): {409},
    ("POST", "/api/v1/robots/{robot_id}/resume"): {409},
    ("POST", "/api/v1/robots/{robot_id}/reset"): {409},
    ("POST", "/api/v1/robots/{robot_id}/claim"): {409},
    ("POST", "/api/v1/robots/{robot_id}/heartbeat"): {409},
    ("POST", "/api/v1/robots/{robot_id}/release"): {409},
    ("POST", "/api/v1/robots/{robot_id}/command"): {409, 429},
    ("GET", "/api/v1/segments/{segment_id}/mcap"): {409, 410},
    ("GET", "/api/v1/policies"): {404},  # an unknown lineage name
    ("POST", "/api/v1/policies"): {404, 409},  # no folder or parent_id; a folder whose policy does not fit
    ("POST", "/api/v1/policies/promote"): {404},
    ("POST", "/api/v1/policies/rollback"): {404, 409},  # no parent to roll back to
    ("POST", "/api/v1/finetune-jobs"): {404, 409},  # an unknown policy; a job already running
}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("contract")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=1e9)  # never asks: stays autonomous
    settings = Settings(
        data_dir=root / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        workers={"kind": "in-process"},
        control_hz=20,
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator", "admin")}
    with Service(settings) as svc, httpx.Client() as client:
        svc.tokens, svc.policy, svc.client = tokens, policy, client
        svc.openapi = client.get(svc.url + "/openapi.json").json()
        yield svc


def _h(svc, role="admin"):
    return {"Authorization": f"Bearer {svc.tokens[role]}"}


def _operations(openapi):
    for path, item in openapi["paths"].items():
        for method, op in item.items():
            yield method.upper(), path, op


def _call(svc, method, path, role="admin", **kw):
    """A request with a valid body where the route takes one (a command, a takeover's label)."""
    body = {"json": COMMAND} if path.endswith("/command") else {}
    if method.upper() == "PATCH" and "/segments/" in path:
        body = {"json": {"label": "good"}}
    return svc.client.request(method, svc.url + path, headers=_h(svc, role), **(body | kw))


def test_every_id_is_bounded_to_the_database_range(service):
    """Ids out of range (huge, negative) are 422 naming the parameter, on every route that takes one; an id
    in range that names nothing is 404 (a path) or matches nothing (a filter). Never a 500."""
    routes = []
    for method, path, op in _operations(service.openapi):
        for param in op.get("parameters", []):
            schema = param["schema"].get("anyOf", [param["schema"]])[0]
            if schema.get("type") == "integer" and (param["in"] == "path" or param["name"].endswith("_id")):
                assert (schema["minimum"], schema["maximum"]) == (0, ID_MAX), (path, param["name"])
                routes.append((method, path, param["in"], param["name"]))
    assert {(p, n) for _, p, _, n in routes} >= {
        ("/api/v1/robots/{robot_id}", "robot_id"),
        ("/api/v1/robots/{robot_id}/command", "robot_id"),
        ("/api/v1/segments/{segment_id}/mcap", "segment_id"),
        ("/api/v1/segments/{segment_id}", "segment_id"),
        ("/api/v1/policies/{version}/activate", "version"),
        ("/api/v1/segments", "robot_id"),
        ("/api/v1/episodes", "robot_id"),
    }
    for method, path, where, name in routes:
        for value in (*OUT_OF_RANGE, UNKNOWN):
            if where == "path":
                r = _call(service, method, path.replace("{" + name + "}", str(value)))
            else:
                r = _call(service, method, path, params={name: value})
            if value == UNKNOWN:
                assert r.status_code == (404 if where == "path" else 200), (method, path, r.text)
                assert where == "path" or r.json() == []
            else:
                assert r.status_code == 422, (method, path, value, r.text)
                assert [e["loc"] for e in r.json()["detail"]] == [[where, name]], r.text
    # the one id in a body: a policy's parent
    api = service.url + "/api/v1/policies"
    for value in OUT_OF_RANGE:
        r = httpx.post(api, json={"path": str(service.policy), "parent_id": value}, headers=_h(service))
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "parent_id"], r.text
    r = httpx.post(api, json={"path": str(service.policy), "parent_id": UNKNOWN}, headers=_h(service))
    assert r.status_code == 404 and f"no policy version {UNKNOWN}" in r.text
    for limit in (0, -1, 1001, 10**30, "ten"):
        for path in ("/api/v1/episodes", "/api/v1/segments"):
            r = _call(service, "GET", path, params={"limit": limit})
            assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "limit"], r.text


def _dependencies(dependant):
    for d in dependant.dependencies:
        yield d
        yield from _dependencies(d)


def _params(dependant, kind):
    return [p for d in (dependant, *_dependencies(dependant)) for p in getattr(d, f"{kind}_params")]


def expected_errors(route: APIRoute, method: str, path: str) -> set[int]:
    """The error statuses a route can answer, from how it is built: a role dependency (401 without a valid
    token, 403 for a weaker role), parameters (422), a body (400 not UTF-8, 413 too large, 422), path ids
    (404 unknown), then what its own code raises (RAISES)."""
    dependant = route.dependant
    out = set()
    if any(getattr(d.call, "role", None) for d in _dependencies(dependant)):
        out |= {401, 403}
    if any(_params(dependant, kind) for kind in ("path", "query", "header", "cookie", "body")):
        out.add(422)
    if _params(dependant, "body"):
        out |= {400, 413}
    if _params(dependant, "path"):
        out.add(404)
    return out | RAISES.get((method, path), set())


def _routes():
    """(method, path as served, route) of every HTTP route of the routers ``create_app`` includes."""
    mounted = [(system.router, "")] + [
        (r, API_PREFIX) for r in (robots.router, assistance.router, records.router, policies.router, finetune.router)
    ]
    for router, prefix in [*mounted, (system.api, API_PREFIX)]:
        for route in router.routes:
            if isinstance(route, APIRoute) and route.include_in_schema:
                (method,) = route.methods
                yield method, prefix + route.path_format, route


def test_every_route_documents_exactly_the_statuses_it_can_answer(service):
    routes = list(_routes())
    keys = {(method, path) for method, path, _ in routes}
    assert keys == {(m, p) for m, p, _ in _operations(service.openapi)}  # every documented route is checked
    for method, path, route in routes:
        op = service.openapi["paths"][path][method.lower()]
        documented = {int(s) for s in op["responses"] if int(s) >= 400}
        assert documented == expected_errors(route, method, path), (method, path)
        for status in documented - {503}:  # /readyz's 503 is its normal body, {"ready": false}
            content = op["responses"][str(status)]["content"]
            assert content == {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}
        if 401 in documented:
            assert "WWW-Authenticate" in op["responses"]["401"]["headers"]
    assert set(RAISES) <= keys  # no declaration for a route that is gone


def test_every_error_answer_has_the_documented_shape(service):
    api, robot = service.url + "/api/v1", service.url + "/api/v1/robots/0"
    answers = {
        400: httpx.post(robot + "/command", content=b'{"gripper": "\xff"}', headers=_h(service, "operator") | JSON),
        401: httpx.get(api + "/robots"),
        403: httpx.post(robot + "/pause", headers=_h(service, "operator")),
        404: httpx.get(api + "/robots/7", headers=_h(service, "viewer")),
        409: httpx.post(robot + "/command", json=COMMAND, headers=_h(service, "operator")),
        413: httpx.post(robot + "/command", content=b"x" * 70_000, headers=_h(service, "operator")),
        422: httpx.post(robot + "/command", json={"delta_pos": [0, 0, "x"]}, headers=_h(service, "operator")),
    }
    for status, r in answers.items():
        assert r.status_code == status, (status, r.text)
        ErrorOut.model_validate(r.json())
        assert r.headers["content-type"] == "application/json"
    assert answers[401].headers["www-authenticate"] == "Bearer"
    assert isinstance(answers[422].json()["detail"], list) and isinstance(answers[409].json()["detail"], str)


def test_metrics_is_documented_and_served_as_text(service):
    op = service.openapi["paths"]["/metrics"]["get"]
    assert list(op["responses"]["200"]["content"]) == ["text/plain"]
    r = httpx.get(service.url + "/metrics", headers=_h(service, "viewer"))
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    assert "hitl_control_ticks_total" in r.text
    assert "hitl_queue_wait_max_seconds" in r.text and "hitl_queue_oldest_unclaimed_seconds" in r.text
    with pytest.raises(json.JSONDecodeError):
        json.loads(r.text)


def test_fixed_length_vectors_have_their_length_in_the_schema(service):
    schemas = service.openapi["components"]["schemas"]

    def array(model, field):
        s = schemas[model]["properties"][field]
        return s.get("anyOf", [s])[0]

    for model, field, n in (
        ("TeleopCommandIn", "delta_pos", 3),
        ("TeleopCommandIn", "delta_rot", 3),
        ("PoseOut", "position", 3),
        ("PoseOut", "quaternion", 4),
    ):
        s = array(model, field)
        assert (s["minItems"], s["maxItems"]) == (n, n), (model, field)
    for field in ("samples", "vectors", "means"):  # lists of 3-vectors
        items = array("UncertaintyOut", field)["items"]
        assert (items["minItems"], items["maxItems"]) == (3, 3), field
    # the server refuses what the schema refuses, with the message clients know
    robot = service.url + "/api/v1/robots/0"
    for bad in ([], [0.0, 0.0], [0.0, 0.0, 0.0, 0.0]):
        for field in ("delta_pos", "delta_rot"):
            body = COMMAND | {field: bad}
            r = httpx.post(robot + "/command", json=body, headers=_h(service, "operator"))
            assert r.status_code == 422 and f"{field} must have 3 components" in r.text, r.text
    view = httpx.get(robot + "/view", headers=_h(service, "viewer")).json()
    assert len(view["pose"]["position"]) == 3 and len(view["pose"]["quaternion"]) == 4
    assert all(len(p["position"]) == 3 and len(p["quaternion"]) == 4 for p in view["bodies"].values())


def test_a_robot_that_exists_is_409_when_not_under_teleop_and_only_an_unknown_one_is_404(service):
    robot = service.url + "/api/v1/robots/0"
    assert httpx.get(robot, headers=_h(service, "viewer")).json()["mode"] == "autonomous"
    r = httpx.post(robot + "/command", json=COMMAND, headers=_h(service, "operator"))
    assert r.status_code == 409 and "autonomous, not under teleop" in r.json()["detail"]
    for action in ("claim", "heartbeat", "release"):
        r = httpx.post(f"{robot}/{action}", headers=_h(service, "operator"))
        assert r.status_code == 409 and "no open assistance request" in r.json()["detail"], (action, r.text)
    for action in ("command", "claim", "heartbeat", "release"):
        r = httpx.post(f"{service.url}/api/v1/robots/1/{action}", json=COMMAND, headers=_h(service, "operator"))
        assert r.status_code == 404 and r.json()["detail"] == "no robot 1", (action, r.text)
    assert httpx.get(robot, headers=_h(service, "viewer")).json()["mode"] == "autonomous"  # nothing changed


def test_policy_paths_the_schema_or_the_os_refuses_are_a_clients_mistake(service):
    """A NUL character is refused by the schema (422); a name longer than the file system's limit is one
    no folder can have (404, as any folder that is not there): never a 500."""
    api = service.url + "/api/v1/policies"
    folder = service.policy.parent  # exists: the OS reaches the long name
    r = service.client.post(api, json={"path": f"{folder}/x\x00y"}, headers=_h(service))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "path"], r.text
    r = service.client.post(api, json={"path": f"{folder}/{'a' * 300}"}, headers=_h(service))
    assert r.status_code == 404 and "cannot be read: File name too long" in r.json()["detail"], r.text
    r = service.client.post(api, json={"path": str(folder / "not-there")}, headers=_h(service))
    assert r.status_code == 404 and "no policy folder" in r.json()["detail"], r.text


def test_a_405_names_every_method_the_path_allows():
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.settings import Settings

    client = TestClient(create_app(Settings()))  # no lifespan: routing and error handling only
    for method, path, allow in (
        ("OPTIONS", "/api/v1/policies", "GET, POST"),  # two routes serve this path
        ("OPTIONS", "/api/v1/finetune-jobs", "GET, POST"),
        ("DELETE", "/api/v1/robots/0/claim", "POST"),
        ("HEAD", "/api/v1/robots", "GET"),  # FastAPI serves no HEAD for a GET route
        ("POST", "/api/v1/robots/3", "GET"),
    ):
        r = client.request(method, path)
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers.get("allow"))
        if method != "HEAD":  # a HEAD answer has no body
            assert r.json() == {"detail": "Method Not Allowed"}  # the one error schema


def test_a_renamed_field_is_kept_for_one_release_marked_deprecated_with_the_new_ones_value(service):
    """One name per concept: the asking signal's score and threshold are ``asking.score`` / ``score`` and
    ``asking.threshold``, the paper's threshold ``paper_threshold``; the old duplicates stay, deprecated."""
    schemas = service.openapi["components"]["schemas"]
    deprecated = {
        "RobotSummary": {"uncertainty", "threshold"},
        "AssistanceRequestOut": {"uncertainty"},
        "PolicyOut": {"threshold"},
    }
    for model, names in deprecated.items():
        props = schemas[model]["properties"]
        assert {n for n, p in props.items() if p.get("deprecated")} == names, model
    [robot] = svc_get(service, "/api/v1/robots")
    assert (robot["uncertainty"], robot["threshold"]) == (robot["asking"]["score"], robot["asking"]["threshold"])
    [policy] = svc_get(service, "/api/v1/policies")
    assert policy["threshold"] == policy["paper_threshold"] is not None


def svc_get(svc, path):
    r = svc.client.get(svc.url + path, headers=_h(svc, "viewer"))
    r.raise_for_status()
    return r.json()

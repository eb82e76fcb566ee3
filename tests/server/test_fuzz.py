"""A bounded property-based fuzz of the service's OpenAPI document with schemathesis, against a real uvicorn
on 127.0.0.1 with an admin token: no answer is a 5xx, every status is one the route documents, and every
answer matches its documented media type and schema.

Every operation of the document is fuzzed, the admin routes included (pause, resume, reset, policy
registration and activation): on in-process workers and one lift-cube robot they stay fast. The robot's
policy asks for help at every step, so claims, heartbeats, commands and releases meet a robot that is
waiting or under teleop, not only 409s."""

import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from server.auth import create_token
from server.db import make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for

EXAMPLES = 12  # per operation and generation mode: about 500 requests in all
KNOWN = {"robot_id": 0, "segment_id": 1, "version": 1, "job_id": 1}  # robot, first segment, policy, job
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    policy = tiny_policy_folder(root / "policy", "lift-cube", threshold=-1.0)  # the robot asks at once
    settings = Settings(
        data_dir=root / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        workers={"kind": "in-process"},
        controller={"budget": 1000},  # a claimed robot stays under teleop while its commands are fuzzed
        control_hz=20,
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    with Service(settings) as svc:
        svc.admin = create_token(sessions, "fuzz-admin", "admin")
        yield svc


def _claim(service) -> httpx.Response:
    url = f"{service.url}/api/v1/robots/{KNOWN['robot_id']}/claim"
    return httpx.post(url, headers={"Authorization": f"Bearer {service.admin}"})


def _fuzz(service, operation, mode, path_parameters, seen: Counter) -> None:
    """EXAMPLES cases of ``operation`` in generation ``mode``, each sent and checked."""
    headers = {"Authorization": f"Bearer {service.admin}"}
    documented = {int(s) for s in operation.definition.raw["responses"]}

    @settings(
        max_examples=EXAMPLES,
        derandomize=True,  # a fixed seed: the same cases every run
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=operation.as_strategy(mode, path_parameters=path_parameters))
    def run(case):
        response = case.call_and_validate(base_url=service.url, headers=headers, checks=CHECKS)
        seen[response.status_code] += 1
        assert response.status_code in documented, (operation.label, response.status_code)  # as the check says

    run()


def test_fuzzing_the_openapi_finds_no_server_error_and_no_undocumented_status(service):
    schema = schemathesis.openapi.from_url(service.url + "/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 20  # every HTTP route of the API (the WebSocket is not in an OpenAPI document)
    seen: dict[str, Counter] = {}
    started = time.monotonic()
    for operation in operations:
        raw = operation.definition.raw
        rounds = [(schemathesis.GenerationMode.POSITIVE, None)]
        if raw.get("parameters") or raw.get("requestBody"):  # something to break: invalid requests too
            rounds.append((schemathesis.GenerationMode.NEGATIVE, None))
        ids = {p["name"] for p in raw.get("parameters", []) if p["in"] == "path"}
        if ids:  # random ids almost never name a record that exists: a round on robot 0 and record 1
            rounds.append((schemathesis.GenerationMode.POSITIVE, {k: KNOWN[k] for k in ids}))
        if operation.path.endswith("/command"):  # commands reach the mailbox only for the robot's holder
            wait_for(lambda: _claim(service).is_success)
        seen[operation.label] = Counter()
        for mode, path_parameters in rounds:
            _fuzz(service, operation, mode, path_parameters, seen[operation.label])
    total = sum(sum(c.values()) for c in seen.values())
    print(f"fuzzed {len(operations)} operations, {total} requests, in {time.monotonic() - started:.1f} s: {seen}")
    assert all(seen.values())  # every operation was called


def test_every_check_and_the_stateful_phase_find_no_failure(service):
    """schemathesis's own runner, as a user runs it against the service: every check (schema-valid
    requests accepted, invalid ones refused, the Allow header of a 405, ...), the coverage, fuzzing and
    stateful phases (sequences that follow the document's links), 30 examples per operation, a fixed
    seed."""
    st = Path(sys.executable).with_name("st")
    cmd = [str(st), "run", f"{service.url}/openapi.json", "--checks", "all", "--seed", "1", "-n", "30"]
    cmd += ["--phases", "examples,coverage,fuzzing,stateful", "--no-color"]
    cmd += ["-H", f"Authorization: Bearer {service.admin}"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
    assert "Stateful" in run.stdout and "generated" in run.stdout  # the phases ran

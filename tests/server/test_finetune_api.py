"""The registry and fine-tuning routes on a real uvicorn: roles, bad requests that change nothing, and an
admin's trigger running a real ``hitl finetune`` process to a recorded gate decision."""

from datetime import UTC, datetime

import httpx
import pytest

from server.auth import create_token
from server.db import SegmentRecord, make_engine, migrate, session_factory
from server.settings import FinetuneSettings, RobotGroup, Settings
from sim.registry import make_task
from tests.helpers import Service, finetunable_policy_folder, free_port, tiny_policy_folder, wait_for, write_segment


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("finetune-api")
    policy = finetunable_policy_folder(root, "lift-cube")
    settings = Settings(
        data_dir=root / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        workers={"kind": "in-process"},
        control_hz=20,
        console=False,
        policy_poll_seconds=0.2,
        finetune=FinetuneSettings(schedule=None, eval_episodes=1, fit_episodes=1, niceness=0),
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator", "admin")}
    with Service(settings) as svc, httpx.Client(base_url=svc.url + "/api/v1", timeout=30) as client:
        svc.tokens, svc.client, svc.sessions, svc.root = tokens, client, sessions, root
        yield svc


def _h(svc, role="admin"):
    return {"Authorization": f"Bearer {svc.tokens[role]}"}


def test_versions_are_listed_with_their_registry_fields(service):
    [row] = service.client.get("/policies", headers=_h(service, "viewer")).json()
    assert row["ref"] == "lift-cube@1" and row["status"] == "active" and row["robots"] == [0]
    assert row["status_reason"] == "configured in the service's settings"
    r = service.client.get("/policies", params={"name": "ghost"}, headers=_h(service, "viewer"))
    assert r.status_code == 404 and "no policy named 'ghost'" in r.json()["detail"]


def test_promote_rollback_and_jobs_refuse_bad_requests_and_weak_roles(service):
    c = service.client
    before = c.get("/policies", headers=_h(service)).json()
    for path, body, status in (
        ("/policies/promote", {"ref": "lift-cube@9"}, 404),
        ("/policies/promote", {"ref": "lift-cube"}, 422),  # which version?
        ("/policies/promote", {"ref": "bad name"}, 422),
        ("/policies/rollback", {"name": "lift-cube"}, 409),  # no parent
        ("/policies/rollback", {"name": "ghost"}, 404),
        ("/finetune-jobs", {"policy": "ghost"}, 404),
        ("/finetune-jobs", {"policy": "lift-cube"}, 422),  # no takeover segments yet
        ("/finetune-jobs", {"policy": "lift-cube", "since": "yesterday"}, 422),
        ("/finetune-jobs", {"policy": "lift-cube", "since": "0h"}, 422),
        ("/finetune-jobs", {"policy": "lift-cube", "since": "999999999999999w"}, 422),
    ):
        r = c.post(path, json=body, headers=_h(service))
        assert r.status_code == status, (path, body, r.text)
    for path, body in (("/policies/promote", {"ref": "lift-cube@1"}), ("/finetune-jobs", {"policy": "lift-cube"})):
        assert c.post(path, json=body, headers=_h(service, "operator")).status_code == 403
    assert c.get("/policies", headers=_h(service)).json() == before
    assert c.get("/finetune-jobs", headers=_h(service, "viewer")).json() == []


def test_an_admin_starts_a_job_and_the_fleet_follows_a_promotion(service):
    c, state = service.client, service.app_state()
    data_dir = state.settings.data_dir
    obs_dim = make_task("lift-cube").obs_spec.dim
    (data_dir / "segments").mkdir(exist_ok=True)
    write_segment(data_dir / "segments" / "api-1.mcap", obs_dim, seed=5)
    with service.sessions() as s:
        s.add(
            SegmentRecord(
                robot_id=0,
                task="lift-cube",
                policy_id=1,
                operator="op",
                reason="test",
                status="closed",
                ended_by="hand-back",
                steps=5,
                path="segments/api-1.mcap",
                ended_at=datetime.now(UTC),
            )
        )
        s.commit()
    r = c.post("/finetune-jobs", json={"policy": "lift-cube@active", "since": "1h"}, headers=_h(service))
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["status"] == "queued" and job["trigger"] == "api" and job["lineage"] == "lift-cube"
    done = wait_for(
        lambda: (
            (j := c.get(f"/finetune-jobs/{job['id']}", headers=_h(service, "viewer")).json())["status"]
            in ("succeeded", "failed")
            and j
        ),
        timeout=300,
    )
    assert done["status"] == "succeeded", done
    assert done["data"]["counts"] == {"segments": 1, "samples": 5, "skipped": 0, "excluded": 0, "waiting": 0}
    assert set(done["evaluation"]["candidate"]["tasks"]) == {"lift-cube"} and "reason" in done["gate"]
    versions = {v["ref"]: v for v in c.get("/policies", headers=_h(service)).json()}
    new = versions["lift-cube@2"]
    assert new["parent_id"] == 1 and new["manifest"]["segments"] == ["segments/api-1.mcap"]
    assert new["calibration"]["episodes"] == ["lift-cube_seed000004.mcap"] and new["command"].startswith("hitl ")
    # whatever the gate said, an admin can promote it: the robot moves at its next episode, and back
    r = c.post("/policies/promote", json={"ref": "lift-cube@2"}, headers=_h(service))
    assert r.status_code == 200 and r.json()["status"] == "active", r.text
    fleet = state.fleet
    wait_for(lambda: fleet.view(0).slot.version == new["id"], timeout=120)
    r = c.post("/policies/rollback", json={"name": "lift-cube"}, headers=_h(service))
    assert r.status_code == 200 and r.json()["ref"] == "lift-cube@1", r.text
    # v2's recalibrated threshold makes the robot ask and hold (its episode waits for an operator): a reset
    # starts the next episode, on the version rolled back to
    assert c.post("/robots/0/reset", headers=_h(service)).status_code == 200
    wait_for(lambda: fleet.view(0).slot.version == 1, timeout=120)
    versions = {v["ref"]: v for v in c.get("/policies", headers=_h(service)).json()}
    assert versions["lift-cube@2"]["status"] == "retired" and versions["lift-cube@1"]["status"] == "active"


def test_registering_a_folder_under_a_parent_adds_the_next_version_of_its_lineage(service, tmp_path):
    folder = tiny_policy_folder(tmp_path / "another", "lift-cube", 1e9)
    r = service.client.post("/policies", json={"path": str(folder), "parent_id": 1}, headers=_h(service))
    assert r.status_code == 201 and r.json()["name"] == "lift-cube" and r.json()["status"] == "candidate", r.text

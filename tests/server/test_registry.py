"""The policy registry: references, versions per lineage, promote and rollback, and the running fleet
following it (hot swap at each robot's next episode), as ``hitl policy`` from another process does."""

import json
import subprocess
import sys

import pytest

from server import registry
from server.db import PolicyVersion
from server.errors import ServiceError
from tests.helpers import tiny_policy_folder
from tests.server.fleet.test_fleet import _fleet


def test_references_parse_or_say_what_is_expected():
    assert registry.PolicyRef.parse("lift-cube") == registry.PolicyRef("lift-cube", None)
    assert registry.PolicyRef.parse("lift-cube@active") == registry.PolicyRef("lift-cube", None)
    assert registry.PolicyRef.parse("lift-cube@12") == registry.PolicyRef("lift-cube", 12)
    assert str(registry.PolicyRef("a", 3)) == "a@3"
    for bad in ("", "@2", "a@0", "a@-1", "a@latest", "a b", "a@2@3", "../x"):
        with pytest.raises(ServiceError) as err:
            registry.PolicyRef.parse(bad)
        assert err.value.status == 422 and "NAME@VERSION" in err.value.message


def _running(fleet, versions):
    for _ in range(12):  # horizon 4: every robot starts a new episode
        fleet.tick()
    return {fleet.view(i).slot.version for i in fleet.robots} == set(versions)


def test_promote_and_rollback_reach_the_fleet_at_the_next_episode(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4, count=2)
    fleet.tick()
    v1 = registry.resolve(fleet.sessions, "policy")
    assert v1.ref == "policy@1" and v1.status == "active"
    folder = tiny_policy_folder(tmp_path / "policy-v2", "lift-cube", 1e9)
    v2 = registry.register(fleet.sessions, folder, "lift-cube", parent=v1.id)
    assert v2.ref == "policy@2" and v2.status == "candidate"
    episode = fleet.view(0).episode_id
    registry.promote(fleet.sessions, "policy@2", "test")  # as `hitl policy promote` does, outside the service
    assert fleet.sync_policies() == [v2.id]  # the fleet's registry watcher
    fleet.tick()
    assert fleet.view(0).slot.version == v1.id and fleet.view(0).episode_id == episode  # finishes its episode
    assert _running(fleet, [v2.id])
    rows = {r.ref: r for r in registry.versions(fleet.sessions, "policy")}
    assert rows["policy@2"].status == "active" and rows["policy@1"].status == "retired"
    assert rows["policy@1"].status_reason == "replaced by policy@2"
    back = registry.rollback(fleet.sessions, "policy")
    assert back.id == v1.id and fleet.sync_policies() == [v1.id]
    assert _running(fleet, [v1.id])
    rows = {r.ref: r for r in registry.versions(fleet.sessions, "policy")}
    assert rows["policy@1"].status == "active" and rows["policy@2"].status == "retired"
    assert rows["policy@2"].status_reason == "rolled back to policy@1"
    fleet.stop()


def test_an_active_version_that_cannot_be_served_leaves_the_fleet_on_its_current_one(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    v1 = registry.resolve(fleet.sessions, "policy")
    folder = tiny_policy_folder(tmp_path / "policy-v2", "lift-cube", 1e9)
    v2 = registry.register(fleet.sessions, folder, "lift-cube", parent=v1.id)
    registry.promote(fleet.sessions, v2.ref)
    (folder / "signals" / "choice-stall" / "config.json").unlink()  # the asking signal (the default) is gone
    assert fleet.sync_policies() == [] and fleet.sync_policies() == []  # reported once, not retried
    assert _running(fleet, [v1.id])
    # through the service's own method it is refused and the registry left as it was
    registry.promote(fleet.sessions, v1.ref)
    with pytest.raises(ServiceError) as err:
        fleet.activate_policy(v2.id)
    assert err.value.status == 422 and "choice-stall" in err.value.message
    assert registry.resolve(fleet.sessions, "policy").id == v1.id
    fleet.stop()


def test_bad_requests_change_nothing(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    before = [(r.id, r.status, r.status_reason) for r in registry.versions(fleet.sessions)]
    for call, status in (
        (lambda: registry.promote(fleet.sessions, "nope@1"), 404),
        (lambda: registry.promote(fleet.sessions, "policy@9"), 404),
        (lambda: registry.rollback(fleet.sessions, "policy"), 409),  # v1 has no parent
        (lambda: registry.rollback(fleet.sessions, "nope"), 404),
        (lambda: registry.register(fleet.sessions, tmp_path, "lift-cube", parent=99), 404),
    ):
        with pytest.raises(ServiceError) as err:
            call()
        assert err.value.status == status
    assert [(r.id, r.status, r.status_reason) for r in registry.versions(fleet.sessions)] == before
    fleet.stop()


def test_the_cli_lists_promotes_and_rolls_back(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    v1 = registry.resolve(fleet.sessions, "policy")
    v2 = registry.register(
        fleet.sessions, tiny_policy_folder(tmp_path / "v2", "lift-cube", 1e9), "lift-cube", parent=v1.id
    )
    fleet.stop()
    base = [sys.executable, "-m", "hitl.cli", "policy"]
    where = ["--data-dir", str(fleet.settings.data_dir)]

    def run(*args):
        return subprocess.run([*base, *args, *where], capture_output=True, text=True, timeout=120)

    listed = run("list", "--json")
    assert listed.returncode == 0, listed.stderr
    assert [(d["ref"], d["status"]) for d in json.loads(listed.stdout)] == [
        ("policy@1", "active"),
        ("policy@2", "candidate"),
    ]
    out = run("promote", "policy@2")
    assert out.returncode == 0 and json.loads(out.stdout)["active"] == "policy@2", out.stderr
    out = run("promote", "policy")
    assert out.returncode == 2 and "NAME@VERSION" in out.stderr
    out = run("promote", "ghost@1")
    assert out.returncode == 2 and "no policy named 'ghost'" in out.stderr
    out = run("rollback", "policy")
    assert out.returncode == 0 and json.loads(out.stdout)["active"] == "policy@1", out.stderr
    with fleet.sessions() as s:
        assert s.get(PolicyVersion, v2.id).status == "retired"
    text = run("list").stdout
    assert "policy@1" in text and "rolled back to policy@1" in text


def test_a_restarted_fleet_serves_the_promoted_version_or_falls_back_when_it_is_gone(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    v1 = registry.resolve(fleet.sessions, "policy")
    folder = tiny_policy_folder(tmp_path / "policy-v2", "lift-cube", 1e9)
    v2 = registry.register(fleet.sessions, folder, "lift-cube", parent=v1.id)
    registry.promote(fleet.sessions, v2.ref)
    fleet.stop()
    again, _ = _fleet(tmp_path, threshold=1e9, horizon=4)  # the same settings and database: a restart
    again.tick()
    assert again.view(0).slot.version == v2.id and registry.resolve(again.sessions, "policy").id == v2.id
    again.stop()
    (folder / "model.safetensors").unlink()
    third, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    third.tick()
    assert third.view(0).slot.version == v1.id  # the configured folder, not a service that cannot start
    assert third.sync_policies() == []
    third.stop()


def test_the_registry_on_postgresql(postgres_url, tmp_path):
    """Every migration applies on PostgreSQL, and versions, promote and rollback behave as on SQLite."""
    from server.db import make_engine, migrate, session_factory

    migrate(postgres_url)
    engine = make_engine(postgres_url)
    sessions = session_factory(engine)
    name = f"pg-{tmp_path.name}"  # the session's database is shared: a lineage of this test's own
    v1 = registry.register(sessions, tiny_policy_folder(tmp_path / "a", "lift-cube", 1.0), "lift-cube", name=name)
    v2 = registry.register(sessions, tiny_policy_folder(tmp_path / "b", "lift-cube", 1.0), "lift-cube", parent=v1.id)
    assert (v1.ref, v2.ref) == (f"{name}@1", f"{name}@2")
    registry.promote(sessions, v1.id)
    registry.promote(sessions, f"{name}@2")
    assert registry.resolve(sessions, name).id == v2.id
    assert registry.rollback(sessions, name).id == v1.id
    assert [r.status for r in registry.versions(sessions, name)] == ["active", "retired"]
    engine.dispose()


def test_one_active_version_per_lineage_is_enforced_by_the_database(tmp_path):
    from sqlalchemy.exc import IntegrityError

    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    v1 = registry.resolve(fleet.sessions, "policy")
    v2 = registry.register(
        fleet.sessions, tiny_policy_folder(tmp_path / "v2", "lift-cube", 1e9), "lift-cube", parent=v1.id
    )
    with fleet.sessions() as s, pytest.raises(IntegrityError):  # a writer that forgets to retire the other
        s.get(PolicyVersion, v2.id).status = "active"
        s.commit()
    odd = tiny_policy_folder(tmp_path / "x@3", "lift-cube", 1e9)
    with pytest.raises(ServiceError) as err:
        registry.register(fleet.sessions, odd, "lift-cube")
    assert err.value.status == 422 and "NAME@VERSION could not address it" in err.value.message
    assert [r.ref for r in registry.versions(fleet.sessions)] == ["policy@1", "policy@2"]
    fleet.stop()


def test_the_registry_records_folders_relative_to_the_data_root(tmp_path, monkeypatch):
    """A version's folder under the data root is recorded relative to it (a database names no machine's
    folders) and opens from there; a row recorded absolute (before) is still found by its folder."""
    from server.db import make_engine, migrate, session_factory

    url = f"sqlite:///{tmp_path / 'hitl.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    monkeypatch.setenv("HITL_DATA_ROOT", str(tmp_path))
    folder = tiny_policy_folder(tmp_path / "var" / "policies" / "lift-cube" / "v1", "lift-cube", 1e9)
    row = registry.register(sessions, folder, "lift-cube", name="lift-cube")
    assert row.path == "var/policies/lift-cube/v1"
    assert registry.folder(row) == folder and registry.register(sessions, folder, "lift-cube").id == row.id
    outside = tiny_policy_folder(tmp_path.parent / f"{tmp_path.name}-elsewhere" / "p", "lift-cube", 1e9)
    other = registry.register(sessions, outside, "lift-cube", name="other")
    assert other.path == str(outside.resolve())  # outside the data root: absolute, the only way to name it
    with sessions() as s:  # a row written before paths were recorded relative
        s.get(PolicyVersion, row.id).path = str(folder.resolve())
        s.commit()
    assert registry.register(sessions, folder, "lift-cube").id == row.id
    monkeypatch.setenv("HITL_DATA_ROOT", str(tmp_path / "moved"))  # the data root moved: relative rows follow it
    with sessions() as s:
        s.get(PolicyVersion, row.id).path = "var/policies/lift-cube/v1"
        s.commit()
    assert (
        registry.folder(registry.resolve(sessions, "lift-cube@1")) == tmp_path / "moved" / "var/policies/lift-cube/v1"
    )

"""Every migration, one at a time, on both back ends the service supports (SQLite and a real PostgreSQL):
rows written before a migration survive it, the schema at head is exactly what the models declare, and
the chain downgrades to nothing and upgrades again."""

import uuid

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect, text

from server.api.schemas import SegmentOut
from server.db import MIGRATIONS, Base, SegmentRecord, make_engine, session_factory
from server.labels import label_of
from storage.lerobot.attempts import TakeoverRequest


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_url(request, tmp_path):
    """The URL of a database with nothing in it: a new SQLite file, or a new database on the session's
    PostgreSQL cluster (dropped afterwards)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'hitl.db'}"
        return
    server = request.getfixturevalue("postgres_url")
    name = f"migrations_{uuid.uuid4().hex[:12]}"
    admin = create_engine(server, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    yield server.rsplit("/", 1)[0] + f"/{name}"
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
    admin.dispose()


def _config(url: str) -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def _revisions(cfg: Config) -> list[str]:
    """Every revision, oldest first (the chain has one head and no branches)."""
    script = ScriptDirectory.from_config(cfg)
    assert len(script.get_heads()) == 1, f"the migrations have several heads: {script.get_heads()}"
    return [r.revision for r in reversed(list(script.walk_revisions()))]


def _columns(engine, table: str) -> set[str]:
    return {c["name"] for c in inspect(engine).get_columns(table)}


def test_each_migration_applies_in_turn_and_keeps_the_rows_written_before_it(empty_url):
    cfg = _config(empty_url)
    revisions = _revisions(cfg)
    assert revisions[:7] == ["0001", "0002", "0003", "0004", "0005", "0006", "0007"]
    engine = make_engine(empty_url)
    try:
        command.upgrade(cfg, "0001")
        with engine.begin() as conn:  # an episode and a takeover segment recorded by a 0001 service
            conn.execute(
                text(
                    "INSERT INTO episodes (id, robot_id, task, seed, steps, assisted_steps, assistance_events,"
                    " started_at) VALUES (1, 0, 'lift-cube', 7, 12, 4, 1, '2026-01-01 00:00:00')"
                )
            )
        segment_columns = _columns(engine, "segments")
        for rev in revisions[1:]:
            command.upgrade(cfg, rev)
            with engine.connect() as conn:
                assert conn.execute(text("SELECT version_num FROM alembic_version")).scalar() == rev
                row = conn.execute(text("SELECT task, seed, steps FROM episodes WHERE id = 1")).one()
            assert tuple(row) == ("lift-cube", 7, 12), f"migration {rev} lost an episode written before it"
            if rev == "0003":
                assert _columns(engine, "segments") == segment_columns | {"ended_by"}
            if rev == "0004":
                assert {"finetune_jobs", "job_leases"} <= set(inspect(engine).get_table_names())
            if rev == "0005":
                assert "console_sessions" in set(inspect(engine).get_table_names())
            if rev == "0006":
                labels = {"label", "discarded", "note", "labelled_by", "labelled_at"}
                assert _columns(engine, "segments") == segment_columns | {"ended_by"} | labels
                with engine.begin() as conn:  # a takeover recorded by a 0006 service: no asking signal stored
                    conn.execute(
                        text(
                            "INSERT INTO segments (id, robot_id, episode_id, task, operator, reason, status, steps,"
                            " path, meta, started_at, discarded) VALUES (1, 0, 1, 'lift-cube', 'op',"
                            " 'spread-stall: stall 2.4x its threshold', 'closed', 3, 'segments/a.mcap', '{}',"
                            " '2026-01-01 00:00:00', false)"
                        )
                    )
            if rev == "0007":
                asked = {"signal", "score", "threshold", "paper_u"}
                assert _columns(engine, "segments") == segment_columns | {"ended_by"} | labels | asked
        # at head, through the models: the takeover recorded at 0006 reads as recorded before, not an error
        with session_factory(engine)() as s:
            row = s.get(SegmentRecord, 1)
            out = SegmentOut.model_validate(row)
            request = label_of(row).request
        assert (out.signal, out.score, out.threshold, out.paper_u) == (None, None, None, None)
        assert out.reason == "spread-stall: stall 2.4x its threshold" and out.steps == 3
        assert request == TakeoverRequest(reason=out.reason)
    finally:
        engine.dispose()


def test_the_schema_at_head_is_what_the_models_declare_and_the_chain_round_trips(empty_url):
    cfg = _config(empty_url)
    command.upgrade(cfg, "head")
    engine = make_engine(empty_url)
    try:
        with engine.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
        assert diff == [], f"the migrations and server/db.py's models disagree: {diff}"
        command.downgrade(cfg, "base")
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
        command.upgrade(cfg, "head")
        with engine.connect() as conn:
            assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
    finally:
        engine.dispose()


OPENER = """
import sys, time
from sqlalchemy import text
from server.db import make_engine
engine = make_engine(sys.argv[1])
time.sleep(max(0.0, float(sys.argv[2]) - time.time()))
with engine.connect() as conn:
    conn.execute(text("SELECT 1"))
"""


def test_processes_opening_a_new_sqlite_database_at_the_same_instant_all_connect(tmp_path):
    """Each connection puts the file in WAL mode if it is not yet; the one that sets it takes a lock the
    others find taken at once ("database is locked", no waiting): they wait for it instead."""
    import subprocess
    import sys
    import time

    url = f"sqlite:///{tmp_path / 'fresh.db'}"
    start = time.time() + 3.0
    procs = [
        subprocess.Popen([sys.executable, "-c", OPENER, url, str(start)], stderr=subprocess.PIPE, text=True)
        for _ in range(6)
    ]
    for p in procs:
        _, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
    engine = create_engine(url)
    with engine.connect() as conn:
        assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"
    engine.dispose()

"""The database lease: one holder at a time, expiry by the database's clock, fencing, and a crashed
holder (a real process killed without releasing) losing it after its ttl."""

import subprocess
import sys
import time

import pytest
from sqlalchemy import text

from policy.checkpoint import save_policy
from server import registry
from server.db import make_engine, migrate, session_factory
from server.errors import ServiceError
from server.lease import Heartbeat, LeaseLost, acquire, holder, release, renew
from tests.helpers import tiny_policy


@pytest.fixture(params=["sqlite", "postgresql"])
def sessions(request, tmp_path):
    """The same lease on both back ends the service supports; PostgreSQL gets every migration first."""
    sqlite = f"sqlite:///{tmp_path / 'hitl.db'}"
    url = sqlite if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    migrate(url)
    engine = make_engine(url)
    if request.param == "postgresql":  # one database for the session: start each test from a free lease
        with engine.begin() as conn:
            conn.execute(text("DELETE FROM job_leases"))
    yield session_factory(engine), url
    engine.dispose()


def test_one_holder_at_a_time_and_release_frees_it(sessions):
    s, _ = sessions
    a = acquire(s, "job", "a", ttl=30)
    assert a is not None and a.fence == 1
    assert acquire(s, "job", "b", ttl=30) is None
    assert holder(s, "job")[0] == "a" and 20 < holder(s, "job")[1] <= 30
    assert acquire(s, "other", "b", ttl=30) is not None  # leases are per name
    assert release(s, a) and holder(s, "job") == (None, None)
    b = acquire(s, "job", "b", ttl=30)
    assert b is not None and b.fence == 2
    assert not release(s, a)  # a's lease is gone: releasing it does not free b's


def test_an_expired_lease_is_taken_over_and_fences_out_the_old_holder(sessions):
    s, _ = sessions
    a = acquire(s, "job", "a", ttl=0.5)
    assert acquire(s, "job", "b", ttl=30) is None
    time.sleep(0.7)
    b = acquire(s, "job", "b", ttl=30)
    assert b is not None and b.fence == a.fence + 1
    with pytest.raises(LeaseLost):
        renew(s, a)
    renew(s, b)  # still b's


def test_a_fenced_registry_write_commits_only_under_the_lease(sessions, tmp_path):
    s, _ = sessions
    folder = tmp_path / "lineage-x"
    save_policy(tiny_policy(), folder)
    a = acquire(s, "job", "a", ttl=0.5)
    time.sleep(0.7)
    b = acquire(s, "job", "b", ttl=30)  # a paused past its ttl, and b took the lease over
    with pytest.raises(LeaseLost):
        registry.register(s, folder, "lift-cube", name="fenced-x", lease=a)
    with pytest.raises(ServiceError, match="no policy named 'fenced-x'"):  # the fenced-out holder wrote nothing
        registry.versions(s, "fenced-x")
    row = registry.register(s, folder, "lift-cube", name="fenced-x", lease=b)
    assert row.ref == "fenced-x@1" and 20 < holder(s, "job")[1] <= 30  # written, and the lease renewed
    with pytest.raises(LeaseLost):
        registry.promote(s, row.id, "gate passed", lease=a)
    assert registry.by_id(s, row.id).status == "candidate"
    assert registry.promote(s, row.id, "gate passed", lease=b).status == "active"


def test_a_heartbeat_keeps_the_lease_past_its_ttl(sessions):
    s, _ = sessions
    a = acquire(s, "job", "a", ttl=0.6)
    with Heartbeat(s, a) as beat:
        time.sleep(1.5)
        assert acquire(s, "job", "b", ttl=30) is None
        beat.check()
    assert not beat.lost.is_set()


CRASHER = """
import os, sys
from server.db import make_engine, session_factory
from server.lease import acquire
s = session_factory(make_engine(sys.argv[1]))
lease = acquire(s, "finetune", "crasher", ttl=1.5)
print("held" if lease else "refused", flush=True)
os._exit(9)  # no release, no cleanup: a crash
"""


def test_a_crashed_holders_lease_expires(sessions):
    s, url = sessions
    out = subprocess.run([sys.executable, "-c", CRASHER, url], capture_output=True, text=True, timeout=60)
    assert out.returncode == 9 and out.stdout.strip() == "held", out.stderr
    assert acquire(s, "finetune", "me", ttl=30) is None and holder(s, "finetune")[0] == "crasher"
    time.sleep(1.6)
    lease = acquire(s, "finetune", "me", ttl=30)
    assert lease is not None and lease.fence == 2


def test_ttl_must_be_positive(sessions):
    s, _ = sessions
    with pytest.raises(ValueError, match="ttl"):
        acquire(s, "job", "a", ttl=0)


def test_the_same_owner_may_take_its_own_lease_again_when_reentrant(sessions):
    s, _ = sessions
    a = acquire(s, "robot/3", "ana", ttl=30, reentrant=True)
    again = acquire(s, "robot/3", "ana", ttl=30, reentrant=True)
    assert again is not None and again.fence == a.fence  # the same holder: the same fence, renewed
    assert acquire(s, "robot/3", "ana", ttl=30) is None  # not reentrant: held is held
    assert acquire(s, "robot/3", "ben", ttl=30, reentrant=True) is None
    assert release(s, again)
    b = acquire(s, "robot/3", "ben", ttl=30, reentrant=True)
    assert b is not None and b.fence == a.fence + 1


CLAIMER = """
import sys, time
from server.db import make_engine, session_factory
from server.lease import acquire
s = session_factory(make_engine(sys.argv[1]))
s().close()  # connected before the start, so that every process reaches the update at once
time.sleep(max(0.0, float(sys.argv[3]) - time.time()))
lease = acquire(s, "robot/7", sys.argv[2], ttl=30, reentrant=True)
print(lease.fence if lease else "refused", flush=True)
"""


def test_parallel_claims_from_separate_processes_give_exactly_one_lease(sessions):
    """Each process stands for an API replica with its own connection pool; all claim one robot at
    the same instant, several times over: one of them holds it each round, every other is refused."""
    s, url = sessions
    for round_ in range(2):
        start = time.time() + 3.0
        procs = [
            subprocess.Popen(
                [sys.executable, "-c", CLAIMER, url, f"replica-{round_}-{i}", str(start)],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for i in range(4)
        ]
        answers = []
        for p in procs:
            out, err = p.communicate(timeout=60)
            assert p.returncode == 0, err
            answers.append(out.strip())
        held = [a for a in answers if a != "refused"]
        assert len(held) == 1, f"round {round_}: {answers}"
        assert int(held[0]) == round_ + 1  # one new holder per round, each fencing out the last
        owner, _ = holder(s, "robot/7")
        assert owner is not None and owner.startswith(f"replica-{round_}-")
        with s() as db:
            db.execute(text("UPDATE job_leases SET owner = NULL, expires_at = 0 WHERE name = 'robot/7'"))
            db.commit()

"""The effort per version and per day that the console's lineage view shows, from a real database."""

from datetime import UTC, datetime, timedelta

from server import effort, registry
from server.db import EpisodeRecord, PolicyVersion, make_engine, migrate, session_factory
from web.panels import lineage_markdown


def _store(tmp_path):
    url = f"sqlite:///{tmp_path / 'hitl.db'}"
    migrate(url)
    return session_factory(make_engine(url))


def test_effort_counts_finished_episodes_per_version_and_day(tmp_path):
    sessions = _store(tmp_path)
    now = datetime.now(UTC)
    with sessions() as s:
        v1 = PolicyVersion(name="lift-cube", version=1, path="policies/lift-cube", task="lift-cube", status="retired")
        s.add(v1)
        s.flush()
        v2 = PolicyVersion(
            name="lift-cube",
            version=2,
            path="var/policies/lift-cube/v2",
            task="lift-cube",
            status="active",
            status_reason="gate passed: lift-hammer 0.10 -> 0.55",
            parent_id=v1.id,
        )
        s.add(v2)
        s.flush()
        yesterday, today = now - timedelta(days=1), now
        rows = [  # (version, started, outcome, requests, assisted steps)
            (v1, yesterday, "success", 2, 30),
            (v1, yesterday, "timeout", 3, 40),
            (v1, yesterday, "reset", 5, 50),  # did not end on its own: not counted
            (v2, today, "success", 0, 0),
            (v2, today, "success", 1, 8),
            (v2, today, None, 1, 4),  # still running
        ]
        for i, (v, started, outcome, events, steps) in enumerate(rows):
            s.add(
                EpisodeRecord(
                    robot_id=i,
                    task="lift-hammer",
                    seed=i,
                    policy_id=v.id,
                    outcome=outcome,
                    assistance_events=events,
                    assisted_steps=steps,
                    started_at=started,
                )
            )
        s.commit()
        ids = v1.id, v2.id
    with sessions() as s:
        per_version = effort.by_version(s)
        per_day = effort.by_day(s, now=now + timedelta(minutes=1))
    assert per_version[ids[0]] == effort.Effort(2, 1, 0, 5, 70)
    assert per_version[ids[1]] == effort.Effort(2, 2, 1, 1, 8)
    assert per_version[ids[1]].autonomous_rate == 0.5 and per_version[ids[0]].assisted_steps_per_episode == 35
    assert per_day[(ids[1], today.date().isoformat())].episodes == 2
    assert per_day[(ids[0], yesterday.date().isoformat())].requests == 5

    [summary] = registry.lineage_summaries(sessions)
    assert [(v.ref, v.status, v.effort.episodes) for v in summary.history] == [
        ("lift-cube@1", "retired", 2),
        ("lift-cube@2", "active", 2),
    ]
    assert [d for d, _ in summary.days] == [yesterday.date().isoformat(), today.date().isoformat()]
    text = lineage_markdown((summary,))
    assert "| lift-cube@2 | active | gate passed: lift-hammer 0.10 -> 0.55 | 2 | 50% | 4.0 | 0.5 |" in text
    assert "| lift-cube@1 | retired | – | 2 | 0% | 35.0 | 2.5 |" in text
    assert f"| {yesterday.date().isoformat()} | 2 | 0% | 35.0 | 2.5 |" in text

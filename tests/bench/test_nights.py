"""``hitl bench nights`` on a tiny fleet: a real ``hitl serve``, its own scheduler on a controlled clock,
the nightly job as the service starts it, a crash of that job, and the report."""

import os
import signal
import time
from datetime import UTC, datetime

import pytest
from sqlalchemy import select

from bench.nights import NightsPlan, Service, _day, _morning, _night, nights_report, run_nights
from bench.nights_quick import quick_config, quick_policy
from server import lease as leases
from server import registry
from server.db import FinetuneJob, PolicyVersion, SegmentRecord
from server.finetune.scheduler import next_due
from tests.helpers import wait_for


@pytest.fixture(scope="module")
def quick_fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("nights")
    return root, quick_policy(root / "quick")


def test_plan_is_validated():
    with pytest.raises(ValueError, match="days"):
        NightsPlan(days=1)
    with pytest.raises(ValueError, match="needs an end"):
        NightsPlan(day_minutes=None, day_episodes=None)
    with pytest.raises(ValueError, match="day-episodes"):
        NightsPlan(day_episodes=0)


def test_a_folder_with_a_service_database_is_refused(tmp_path):
    (tmp_path / "hitl.db").write_bytes(b"")
    with pytest.raises(ValueError, match="already holds a service database"):
        run_nights(NightsPlan(data_dir=tmp_path))


def test_days_and_nights_through_the_service_with_a_crash_mid_night(quick_fleet):
    """Day 1: the robots ask, the operator bot drives, the service records takeovers. Night 1: the
    benchmark moves the service's clock, the service's scheduler starts the job, the job is killed
    with SIGKILL in training: the registry is unchanged. Night 2: the scheduler starts the job again,
    which resumes the killed one under the lease, trains on the segments the service recorded, and
    its gate decides: a refused candidate leaves the fleet on its version and the report says why, a
    promoted one becomes active. Day 2 runs on the version the gate left active and the report counts it."""
    root, policy = quick_fleet
    config = quick_config(root, policy)
    plan = NightsPlan(config=config, days=2, day_minutes=3.0, day_episodes=1, data_dir=root / "service", progress=False)
    service = Service(plan, plan.data_dir)
    sessions = service.sessions
    days, nights = [], []
    try:
        service.wait_ready()
        days.append(_day(service, plan, 1))
        with sessions() as s:
            recorded = {seg.id for seg in s.scalars(select(SegmentRecord).where(SegmentRecord.status == "closed"))}
            versions_before = [(v.id, v.status) for v in s.scalars(select(PolicyVersion))]
        assert recorded, "day 1 recorded no takeover"
        # the report so far, as run_nights hands it on after every day: day 1 counted, marked incomplete
        so_far = nights_report(sessions, service.settings, plan, days, [], complete=False)
        assert so_far["complete"] is False and len(so_far["days"]) == 1
        assert so_far["days"][0]["per_task"]["lift-cube"]["episodes"] >= 1

        # night 1: the scheduler fires on the moved clock; the job is killed while it trains
        night_start = datetime.now(UTC)
        due = next_due(service.schedule, service.clock)
        service.set_clock(due)

        def training():
            with sessions() as s:
                job = s.scalars(select(FinetuneJob).where(FinetuneJob.created_at >= night_start)).first()
            return job if job is not None and job.stage == "train" else None

        job = wait_for(training, timeout=180)
        owner, _ = leases.holder(sessions, leases.FINETUNE_LEASE)
        assert owner is not None and job.trigger == "schedule"
        os.kill(int(owner.split(":")[1]), signal.SIGKILL)
        wait_for(lambda: service.schedule_state()["last_exit_code"] == -signal.SIGKILL, timeout=30)
        with sessions() as s:
            assert [(v.id, v.status) for v in s.scalars(select(PolicyVersion))] == versions_before
            assert s.get(FinetuneJob, job.id).status == "running"  # its holder is gone, its row says so later
        time.sleep(6)  # the killed job's lease (5 s in the quick settings) lapses

        # night 2: the scheduler fires again; the job resumes the killed one and its gate decides
        nights.append(_night(service, plan, 2))
        [ran] = [j for j in nights[0]["jobs"] if j["status"] != "interrupted"] or [None]
        assert nights[0]["exit_code"] == 0, nights
        assert ran is not None and ran["job"] == job.id and ran["resumes"] == 1, nights
        assert ran["status"] == "succeeded" and ran["trigger"] == "schedule"
        assert ran["data"]["segments"] >= 1 and ran["data"]["samples"] >= 1
        with sessions() as s:
            used = set(s.get(FinetuneJob, job.id).data["segment_ids"])
        assert used and used <= recorded  # the takeovers the service recorded on day 1
        # the gate decides on its evidence: a candidate trained on a few takeovers may or may not lift the hammer
        # on the 2 evaluation seeds, so either way the registry and the next day must follow its decision
        promoted = ran["promoted"]
        assert promoted is ran["gate"]["promote"]
        if not promoted:
            assert ran["gate"]["reason"].startswith("not better on lift-hammer")
        assert ran["gate"]["evidence"]["target_tasks"] == ["lift-hammer"]
        assert ran["version"] == "policy@2" and ran["parent"] == "policy@1"
        serving = "policy@2" if promoted else "policy@1"
        assert registry.resolve(sessions, "policy@active").ref == serving

        _morning(service, due.replace(hour=8))
        days.append(_day(service, plan, 2))
    finally:
        service.stop()
    report = nights_report(sessions, service.settings, plan, days, nights)
    assert report["complete"] is True
    day1, day2 = report["days"]
    for day in (day1, day2):
        for task in ("lift-cube", "lift-hammer"):
            t = day["per_task"][task]
            assert t["episodes"] >= 1, (task, day, days[0].bot, days[-1].bot)
            # day 1 ran on policy@1; day 2 on what the gate left active (a refused candidate never serves)
            assert t["versions"] == {("policy@1" if day is day1 else serving): t["episodes"]}
            helped, assisted = t["assisted_steps_per_helped_episode"], t["assisted_steps_per_episode"]
            if day is day2 and promoted:
                # a promoted version's choice-stall thresholds were fitted on its own episodes by the job:
                # it asks where its scores say so, possibly never in a short day; what it asked is its signal's
                assert set(t["takeovers_by_cause"]) <= {"choice-stall"}, t
                assert (helped is None) == (not assisted) and (helped is None or helped >= assisted), t
                continue
            assert helped >= assisted
            # policy@1's signal asks at once (its threshold is under every score): no watchdog
            assert t["requests_per_episode"] > 0, (task, day, days[0].bot, days[-1].bot)
            assert t["assisted_steps_per_episode"] > 0 and t["operator_seconds_per_episode"] > 0
            assert set(t["takeovers_by_cause"]) == {"choice-stall"}, t
    assert report["nights"][0]["jobs"][0]["gate"]["promote"] is promoted
    assert report["goals"]["day2"]["assisted_steps_ratio"] is not None
    assert day2["clock"].startswith(due.date().isoformat())


def test_job_errors_name_paths_relative_to_the_data_root(tmp_path, monkeypatch):
    from bench.nights import _portable_text

    monkeypatch.setenv("HITL_DATA_ROOT", str(tmp_path))
    assert _portable_text(f"not in {tmp_path}/data/demos/x (e.g. a.mcap)") == "not in data/demos/x (e.g. a.mcap)"
    assert _portable_text(None) is None


def test_a_night_whose_job_does_not_end_stops_the_run_and_the_report_says_so(quick_fleet):
    """A night's job still running at ``night_timeout_s`` stops the run with what it measured: one day,
    the night marked timed out, and the report not complete."""
    root, policy = quick_fleet
    plan = NightsPlan(
        config=quick_config(root, policy),
        days=3,
        day_minutes=0.2,  # long enough for the bot's first takeovers, which give the night's job data
        night_timeout_s=1.0,
        data_dir=root / "short-night",
        progress=False,
    )
    report = run_nights(plan)
    assert report["complete"] is False
    assert len(report["days"]) == 1 and len(report["nights"]) == 1
    assert report["nights"][0]["timed_out"] is True and report["nights"][0]["exit_code"] is None

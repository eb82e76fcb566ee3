"""``hitl bench nights`` on a tiny fleet: a real ``hitl serve``, its own scheduler on a controlled clock,
the nightly job as the service starts it, a crash of that job, and the report."""

import json
import os
import signal
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

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


def _parent_succeeds_on_every_hammer_seed(sessions, ref: str, finetune: dict) -> dict:
    """The parent's evaluation as the registry holds it, fixed: every lift-hammer seed of the gate lifted,
    no lift-cube seed. The job reuses a parent's recorded results on the same seeds (``_parent_eval``),
    so no candidate can be better on the hammer and none can be worse on the cube: the gate must refuse,
    on the hammer, whatever the candidate learnt from the day's takeovers."""
    from policy.finetune import TaskResult

    n, seed = finetune["eval_episodes"], finetune.get("eval_seed", 50_000)
    tasks = {"lift-cube": TaskResult("lift-cube", n, 0, seed), "lift-hammer": TaskResult("lift-hammer", n, n, seed)}
    doc = {"episodes": n, "seed": seed, "tasks": {t: r.to_dict() for t, r in tasks.items()}}
    with sessions() as s:
        row = s.get(PolicyVersion, registry.resolve(sessions, ref).id)
        row.evaluation = {**(row.evaluation or {}), **doc}
        s.commit()
    return doc


def _ask_under_every_score(version: Path, threshold: float) -> None:
    """The version's choice-stall threshold set under every score (as ``quick_policy`` sets policy@1's),
    so that a robot on it asks at once, every episode."""
    path = version / "signals" / "choice-stall" / "config.json"
    doc = json.loads(path.read_text())
    doc["calibration"]["threshold"] = threshold
    path.write_text(json.dumps(doc, indent=2))


def test_days_and_nights_through_the_service_with_a_crash_mid_night(quick_fleet):
    """Day 1: the robots ask, the operator bot drives, the service records takeovers. Night 1: the
    benchmark moves the service's clock, the service's scheduler starts the job, the job is killed
    with SIGKILL in training: the registry is unchanged. Night 2: the scheduler starts the job again,
    which resumes the killed one under the lease, trains on the segments the service recorded, and
    its gate refuses the candidate (the parent's recorded evaluation lifts the hammer on every seed, so
    no candidate is better there): the fleet stays on its version and the report says why. Day 2 runs on
    that version, whose signal asks at once, and the report counts it. An admin then promotes the refused
    candidate, its signal's threshold set under every score: day 3 runs on it, and its own signal asks."""
    root, policy = quick_fleet
    config = quick_config(root, policy, eval_episodes=1, fit_episodes=1)  # one gate seed per task: the plumbing
    plan = NightsPlan(config=config, days=3, day_minutes=3.0, day_episodes=1, data_dir=root / "service", progress=False)
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
        fixed = _parent_succeeds_on_every_hammer_seed(sessions, "policy@1", service.settings.finetune.model_dump())

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

        # night 2: the scheduler fires again; the job resumes the killed one and its gate refuses
        nights.append(_night(service, plan, 2))
        [ran] = [j for j in nights[0]["jobs"] if j["status"] != "interrupted"] or [None]
        assert nights[0]["exit_code"] == 0, nights
        assert ran is not None and ran["job"] == job.id and ran["resumes"] == 1, nights
        assert ran["status"] == "succeeded" and ran["trigger"] == "schedule"
        assert ran["data"]["segments"] >= 1 and ran["data"]["samples"] >= 1
        with sessions() as s:
            used = set(s.get(FinetuneJob, job.id).data["segment_ids"])
        assert used and used <= recorded  # the takeovers the service recorded on day 1
        assert ran["promoted"] is False and ran["gate"]["promote"] is False, ran["gate"]
        assert ran["gate"]["reason"].startswith("not better on lift-hammer: ") and ran["gate"]["reason"].endswith(
            " against 1.00"
        ), ran["gate"]
        evidence = ran["gate"]["evidence"]
        assert evidence["target_tasks"] == ["lift-hammer"] and evidence["target_success"]["parent"] == 1.0
        assert evidence["per_task"]["lift-hammer"]["parent"] == fixed["tasks"]["lift-hammer"]
        # the candidate itself was rolled out on the gate's seeds
        assert evidence["per_task"]["lift-hammer"]["candidate"]["episodes"] == fixed["episodes"]
        assert ran["version"] == "policy@2" and ran["parent"] == "policy@1"
        assert registry.resolve(sessions, "policy@active").ref == "policy@1"

        _morning(service, due.replace(hour=8))
        days.append(_day(service, plan, 2))

        # an admin promotes the refused candidate anyway; its own signal, carried by the job, asks at once
        candidate = registry.folder(registry.resolve(sessions, "policy@2"))
        assert "choice-stall" in json.loads((candidate / "calibration.json").read_text())["signals"]
        _ask_under_every_score(candidate, -2.0)  # policy@1's is -1.0: the segments say whose signal asked
        r = service.api.post("/policies/promote", json={"ref": "policy@2", "reason": "the test promotes it"})
        assert r.status_code == 200, r.text
        assert registry.resolve(sessions, "policy@active").ref == "policy@2"
        _morning(service, due.replace(hour=8) + timedelta(days=1))
        days.append(_day(service, plan, 3))
    finally:
        service.stop()
    report = nights_report(sessions, service.settings, plan, days, nights)
    assert report["complete"] is True
    day1, day2, day3 = report["days"]
    for day, serving in ((day1, "policy@1"), (day2, "policy@1"), (day3, "policy@2")):
        for task in ("lift-cube", "lift-hammer"):
            t = day["per_task"][task]
            assert t["episodes"] >= 1 and t["requests_per_episode"] > 0, (task, day, days[0].bot, days[-1].bot)
            assert t["assisted_steps_per_episode"] > 0 and t["operator_seconds_per_episode"] > 0
            # the refused candidate never served; the promoted one served every episode of day 3
            assert t["versions"] == {serving: t["episodes"]}
            # the serving version's signal asks at once (its threshold is under every score): no watchdog
            assert set(t["takeovers_by_cause"]) == {"choice-stall"}, t
            assert t["assisted_steps_per_helped_episode"] >= t["assisted_steps_per_episode"]
    # the requests of each day were made by the signal of the version that served it: its threshold
    with sessions() as s:
        for window, threshold in zip(days, (-1.0, -1.0, -2.0), strict=True):
            opened = select(SegmentRecord).where(
                SegmentRecord.started_at >= window.started, SegmentRecord.started_at < window.ended
            )
            asked = [(g.signal, g.threshold) for g in s.scalars(opened)]
            assert asked and set(asked) == {("choice-stall", threshold)}, (window.clock, asked)
    assert report["nights"][0]["jobs"][0]["gate"]["promote"] is False
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

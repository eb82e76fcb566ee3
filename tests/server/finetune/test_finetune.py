"""The fine-tuning job end to end on a tiny policy: real MCAP segments and episodes, a real SQLite store,
evaluation in the real simulator through the controller."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from policy.checkpoint import load_calibration, read_info
from policy.finetune import FinetuneConfig
from server import registry
from server.db import (
    EpisodeRecord,
    FinetuneJob,
    PolicyVersion,
    SegmentRecord,
    make_engine,
    migrate,
    session_factory,
)
from server.errors import ServiceError
from server.finetune.job import FinetuneRunner, JobBusy
from server.finetune.plan import JobRequest, parse_since
from server.lease import FINETUNE_LEASE, acquire, release
from sim.registry import make_task
from tests.helpers import finetunable_policy_folder, write_segment

TASK = "lift-cube"
LABELS = make_task(TASK).obs_spec.labels()
TINY = FinetuneConfig(steps=12, batch_size=8, checkpoint_every=5, eval_episodes=1, min_steps=1, fit_episodes=1)


def _closed_segment(name: str, policy_id: int, ended_at: datetime, **kw) -> SegmentRecord:
    """The row of segments/<name>.mcap: a 5-step takeover the operator handed back."""
    return SegmentRecord(
        robot_id=0,
        task="lift-nut",
        policy_id=policy_id,
        operator="op",
        reason="test",
        status="closed",
        ended_by="hand-back",
        steps=5,
        path=f"segments/{name}.mcap",
        ended_at=ended_at,
        **kw,
    )


@pytest.fixture
def store(tmp_path):
    """A data folder with a registered active tiny policy (pretrained on 5 synthetic episodes), two good
    takeover segments and one corrupt one, all closed. The policy and its episodes record the task's
    observation layout, as ``hitl train`` and ``hitl demos`` do; the segments record none (as older ones)."""
    obs_dim = make_task(TASK).obs_spec.dim
    data_dir = tmp_path / "var"
    folder = finetunable_policy_folder(tmp_path, TASK, obs_labels=LABELS)
    url = f"sqlite:///{data_dir / 'hitl.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    row = registry.register(sessions, folder, TASK, status="active")
    seg_dir = data_dir / "segments"
    seg_dir.mkdir(parents=True)
    write_segment(seg_dir / "good-1.mcap", obs_dim, seed=1)
    write_segment(seg_dir / "good-2.mcap", obs_dim, seed=2)
    (seg_dir / "broken.mcap").write_bytes(b"\x89MCAP0\r\n" + b"garbage" * 10)
    now = datetime.now(UTC)
    with sessions() as s:
        for name in ("good-1", "broken", "good-2"):
            s.add(_closed_segment(name, row.id, now))
        s.add(
            SegmentRecord(
                robot_id=1,
                task="lift-nut",
                policy_id=row.id,
                operator="op",
                reason="test",
                status="open",
                steps=3,
                path="segments/open.mcap",
            )
        )
        s.commit()
    return sessions, data_dir, row


def _snapshot(sessions) -> list[tuple]:
    with sessions() as s:
        versions = [(r.id, r.name, r.version, r.status, r.path) for r in s.scalars(select(PolicyVersion))]
        jobs = [(j.id, j.status) for j in s.scalars(select(FinetuneJob))]
    return versions + jobs


def test_a_job_makes_a_recalibrated_evaluated_version_and_records_the_gate(store):
    sessions, data_dir, parent = store
    lines = []
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lines.append)
    [summary] = runner.run(JobRequest(policy="lift-cube@active", config=TINY))
    assert summary["status"] == "succeeded", summary
    child = registry.resolve(sessions, summary["version"])
    assert child.ref == "lift-cube@2" and child.parent_id == parent.id
    # the corrupt segment is named with its reason and skipped; the open one is never used
    assert any("broken.mcap" in line for line in lines)
    with sessions() as s:
        job = s.get(FinetuneJob, summary["job"])
    assert job.status == "succeeded" and job.version_id == child.id and job.progress == 1.0
    assert set(job.data["skipped"]) == {"broken.mcap"} and job.data["counts"]["samples"] == 10
    assert child.manifest["segments"] == ["segments/good-1.mcap", "segments/good-2.mcap"]
    assert child.manifest["pretraining"]["episodes"] == read_info(parent.path)["dataset"]["train_episodes"]
    # a recalibrated threshold on the held-out episode, carried into the folder, its signals recalibrated
    cal = load_calibration(child.path)
    assert child.threshold == pytest.approx(cal["threshold"]) and cal["episodes"] == ["lift-cube_seed000004.mcap"]
    assert child.calibration["episodes"] == cal["episodes"] and {"spread", "choice-stall"} <= set(cal["signals"])
    for name in ("spread", "choice-stall"):
        assert (Path(child.path) / "signals" / name / "config.json").is_file()
    # the fleet's signal fitted on the candidate's own episodes: lift-cube its familiar scene, lift-nut a new
    # one; the tiny policy lifts nothing, so nothing is raised
    assert {"choice-stall"} <= set(cal["signals_fitted_on_own_episodes"])
    fitted = cal["signals_fitted_on_own_episodes"]["choice-stall"]
    assert fitted["familiar"]["tasks"] == ["lift-cube"] and fitted["new"]["tasks"] == ["lift-nut"]
    assert fitted["new"]["seed"] == 60_000 and fitted["new"]["successes"] == 0 and fitted["new"]["factor"] is None
    # evaluated on the training task and the takeovers' task, parent on the same seeds; a gate decision
    assert set(job.evaluation["candidate"]["tasks"]) == {"lift-cube", "lift-nut"}
    assert job.evaluation["parent"]["seed"] == job.evaluation["candidate"]["seed"]
    assert job.gate["evidence"]["target_tasks"] == ["lift-nut"] and "promote" in job.gate
    expected = "active" if job.gate["promote"] else "candidate"
    assert child.status == expected and child.status_reason.startswith("gate ")
    assert registry.resolve(sessions, "lift-cube").id == (child.id if job.gate["promote"] else parent.id)
    info = read_info(child.path)
    assert info["finetune"]["job"] == job.id and info["finetune"]["manifest"]["parent"] == "lift-cube@1"
    assert info["obs_labels"] == LABELS  # the parent's layout carried forward: the child is checked as it was


@pytest.mark.parametrize(
    ("request_kw", "status", "needle"),
    [
        ({"policy": "no-such-policy"}, 404, "no policy named 'no-such-policy'"),
        ({"policy": "lift-cube@7"}, 404, "no policy lift-cube@7"),
        ({"policy": "lift-cube", "since": timedelta(seconds=1)}, 422, "no closed or recovered takeover segments"),
        ({"policy": "bad name!"}, 422, "bad policy reference"),
    ],
)
def test_bad_input_is_refused_and_changes_nothing(store, request_kw, status, needle):
    sessions, data_dir, _ = store
    before = _snapshot(sessions)
    if "since" in request_kw:  # the segments ended a minute ago: none in a 1 s window
        with sessions() as s:
            for seg in s.scalars(select(SegmentRecord)):
                seg.ended_at = datetime.now(UTC) - timedelta(minutes=1)
            s.commit()
    with pytest.raises(ServiceError) as err:
        FinetuneRunner(sessions, data_dir, progress=False).run(JobRequest(config=TINY, **request_kw))
    assert err.value.status == status and needle in err.value.message
    assert _snapshot(sessions) == before


def test_only_corrupt_segments_fail_the_job_with_their_names_and_register_nothing(store):
    sessions, data_dir, parent = store
    for name in ("good-1", "good-2"):
        (data_dir / "segments" / f"{name}.mcap").write_bytes(b"not an mcap file")
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(JobRequest(policy="lift-cube", config=TINY))
    assert summary["status"] == "failed" and "good-1.mcap" in summary["error"]
    assert [v.ref for v in registry.versions(sessions, "lift-cube")] == ["lift-cube@1"]
    with sessions() as s:
        job = s.scalars(select(FinetuneJob)).one()
    assert job.status == "failed" and "no usable sample" in job.error and job.version_id is None


def test_takeovers_recorded_with_another_observation_layout_are_not_trained_on_and_named(store):
    sessions, data_dir, parent = store
    # the same size as the policy's observation, the object's extent (and the finger rays after it) where its
    # position was
    moved = LABELS[:11] + LABELS[23:] + LABELS[11:23]
    for i, name in enumerate(("good-1", "good-2")):
        write_segment(data_dir / "segments" / f"{name}.mcap", len(LABELS), seed=i, obs_labels=moved)
    lines = []
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lines.append)
    [summary] = runner.run(JobRequest(policy="lift-cube", config=TINY))
    assert summary["status"] == "failed" and "no usable sample" in summary["error"]
    why = (
        "recorded with another observation layout than the policy's (task lift-nut, observations [eef_pos(3), "
        "eef_rot6d(6), gripper_qpos(2), object_extent(3), finger_rays(6), object_pos(3), object_rot6d(6), "
        "object_to_eef_pos(3)]): the same channels in another order (at channel 11: object_extent, not object_pos)"
    )
    assert f"good-1.mcap: {why}" in summary["error"] and any(f"skipped segment good-2.mcap: {why}" in x for x in lines)
    assert [v.ref for v in registry.versions(sessions, "lift-cube")] == ["lift-cube@1"]
    # one segment of the policy's layout: the job trains on it alone, the other named in data.skipped
    write_segment(data_dir / "segments" / "good-2.mcap", len(LABELS), seed=2, obs_labels=LABELS)
    [summary] = runner.run(JobRequest(policy="lift-cube", config=TINY, promote=False))
    assert summary["status"] == "succeeded", summary
    with sessions() as s:
        job = s.get(FinetuneJob, summary["job"])
    assert job.data["skipped"]["good-1.mcap"] == why and job.data["counts"]["samples"] == 5


def test_episodes_recorded_with_another_observation_layout_are_refused_naming_the_files(store, tmp_path):
    from storage import keys
    from storage.episodes import EpisodeWriter

    sessions, data_dir, _ = store
    extra = tmp_path / "extra"
    moved = LABELS[:11] + LABELS[23:] + LABELS[11:23]  # the same size: the dataset itself loads
    for name, labels in (("lift.mcap", LABELS), ("moved.mcap", moved)):
        with EpisodeWriter(extra / name, {"task": "x", "seed": 0, "obs_labels": labels}, object_names=[]) as w:
            act = [0.0, 0.0, 0.9, 0, 1, 0, 1, 0, 0, -1.0]
            w.write_step(0, [0.0] * len(labels), act, act[:3], [0, 0, 0, 1.0], 0.04, True, keys.SOURCE_EXPERT)
            w.finish(True, 1, "success")
    request = JobRequest(policy="lift-cube", source="full-episodes", episodes=extra, config=TINY)
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(request)
    assert summary["status"] == "failed"
    assert summary["error"] == (
        f"1 episode(s) of {extra} were recorded with another observation layout than the policy's [eef_pos(3), "
        "eef_rot6d(6), gripper_qpos(2), object_pos(3), object_rot6d(6), object_to_eef_pos(3), object_extent(3), "
        "finger_rays(6)]: "
        "moved.mcap: recorded with another observation layout ([eef_pos(3), eef_rot6d(6), gripper_qpos(2), "
        "object_extent(3), finger_rays(6), object_pos(3), object_rot6d(6), object_to_eef_pos(3)]): the same channels "
        "in another order (at channel 11: object_extent, not object_pos)"
    )


def test_a_gate_task_the_parent_cannot_run_fails_the_job_before_it_trains(store):
    sessions, data_dir, _ = store
    request = JobRequest(policy="lift-cube", config=TINY, eval_tasks=("lift-nut", "open-drawer"))
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(request)
    assert summary["status"] == "failed" and "cannot run task open-drawer" in summary["error"]
    assert "missing object_pos, object_rot6d, object_to_eef_pos, object_extent, finger_rays" in summary["error"]
    assert not (data_dir / "finetune" / "job-1" / "train").exists()  # nothing trained


def test_a_second_job_is_refused_while_the_lease_is_held(store):
    sessions, data_dir, _ = store
    held = acquire(sessions, FINETUNE_LEASE, "other-host:1", ttl=60)
    before = _snapshot(sessions)
    with pytest.raises(JobBusy, match="other-host:1"):
        FinetuneRunner(sessions, data_dir, progress=False).run(JobRequest(policy="lift-cube", config=TINY))
    assert _snapshot(sessions) == before
    release(sessions, held)


def test_an_interrupted_job_resumes_from_its_checkpoint(store, monkeypatch):
    sessions, data_dir, _ = store
    import policy.train as train

    real = train.TrainState.save
    calls = []

    def crash_after_first_checkpoint(self, folder):
        real(self, folder)
        calls.append(self.step)
        if len(calls) == 1:
            raise KeyboardInterrupt  # as SIGTERM does in `hitl finetune`

    monkeypatch.setattr(train.TrainState, "save", crash_after_first_checkpoint)
    runner = FinetuneRunner(sessions, data_dir, progress=False)
    with pytest.raises(KeyboardInterrupt):
        runner.run(JobRequest(policy="lift-cube", config=TINY))
    with sessions() as s:
        job = s.scalars(select(FinetuneJob)).one()
    assert job.status == "interrupted" and calls == [5]
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(JobRequest(policy="lift-cube", config=TINY))
    assert summary["job"] == job.id and summary["status"] == "succeeded"
    info = read_info(registry.resolve(sessions, summary["version"]).path)
    assert info["finetune"]["history"]["resumed_from_step"] == 5 and calls == [5, 10, 12]


def test_with_no_policy_only_lineages_with_new_segments_run(store):
    sessions, data_dir, _ = store
    runner = FinetuneRunner(sessions, data_dir, progress=False)
    assert [p.lineage for p in runner.plan(JobRequest())] == ["lift-cube"]
    runner.run(JobRequest(config=TINY))
    assert runner.plan(JobRequest()) == []  # every segment is in a version's manifest now
    assert runner.run(JobRequest(config=TINY)) == []


def test_a_job_on_successful_episodes_leaves_out_the_rest_and_waits_for_running_ones(store):
    sessions, data_dir, parent = store
    obs_dim = make_task(TASK).obs_spec.dim
    write_segment(data_dir / "segments" / "timed-out.mcap", obs_dim, seed=3)
    write_segment(data_dir / "segments" / "running.mcap", obs_dim, seed=4)
    with sessions() as s:
        episodes = {
            o: EpisodeRecord(robot_id=0, task="lift-nut", seed=1, outcome=o) for o in ("success", "timeout", None)
        }
        s.add_all(episodes.values())
        s.flush()
        for seg in s.scalars(select(SegmentRecord)):  # the fixture's takeovers were in a successful episode
            seg.episode_id = episodes["success"].id
        for name, outcome in (("timed-out", "timeout"), ("running", None)):
            s.add(_closed_segment(name, parent.id, datetime.now(UTC), episode_id=episodes[outcome].id))
        s.commit()
        ids = {Path(seg.path).stem: seg.id for seg in s.scalars(select(SegmentRecord))}
        ids["timed-out-episode"] = episodes["timeout"].id
        running_episode = episodes[None].id
    lines = []
    cfg = replace(TINY, successful_only=True, takeover_tail=3)
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lines.append)
    [summary] = runner.run(JobRequest(policy="lift-cube", config=cfg))
    assert summary["status"] == "succeeded", summary
    with sessions() as s:
        job = s.get(FinetuneJob, summary["job"])
    # two good 5-step takeovers of the successful episode, their last 3 steps each; the corrupt one skipped
    assert job.data["counts"] == {"segments": 2, "samples": 6, "skipped": 1, "excluded": 1, "waiting": 1}
    assert job.data["excluded"] == {"timed-out.mcap": "its episode ended in timeout (successful episodes only)"}
    assert any("running.mcap waits for its episode to end" in line for line in lines)
    child = registry.resolve(sessions, summary["version"])
    assert child.manifest["segment_ids"] == [ids["good-1"], ids["good-2"]]
    assert child.manifest["excluded_segment_ids"] == [ids["timed-out"]]
    config = read_info(child.path)["finetune"]["config"]
    assert config["successful_only"] is True and config["takeover_tail"] == 3
    # the left-out takeover is not news the next night, nor is a new one the selection leaves out; the
    # running one is, once its episode has succeeded
    nightly = JobRequest(config=cfg)
    assert runner.plan(nightly) == []
    write_segment(data_dir / "segments" / "timed-out-2.mcap", obs_dim, seed=5)
    with sessions() as s:
        s.add(_closed_segment("timed-out-2", parent.id, datetime.now(UTC), episode_id=ids["timed-out-episode"]))
        s.commit()
    assert runner.plan(nightly) == []
    assert [p.lineage for p in runner.plan(JobRequest(config=TINY))] == ["lift-cube"]  # news without the selection
    with sessions() as s:
        s.get(EpisodeRecord, running_episode).outcome = "success"
        s.commit()
    assert [p.lineage for p in runner.plan(nightly)] == ["lift-cube"]


def test_a_job_whose_takeovers_are_all_left_out_or_waiting_fails_and_says_why(store):
    sessions, data_dir, _ = store
    with sessions() as s:
        episode = EpisodeRecord(robot_id=0, task="lift-nut", seed=1, outcome=None)
        s.add(episode)
        s.flush()
        for seg in s.scalars(select(SegmentRecord)):
            seg.episode_id = episode.id if seg.path.endswith("good-1.mcap") else None
        s.commit()
    request = JobRequest(policy="lift-cube", config=replace(TINY, successful_only=True))
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(request)
    assert summary["status"] == "failed"
    assert "0 segment(s) skipped, 2 left out by the selection, 1 waiting for their episode to end" in summary["error"]
    assert "no episode recorded for it" in summary["error"]
    assert [v.ref for v in registry.versions(sessions, "lift-cube")] == ["lift-cube@1"]


def test_a_discarded_takeover_is_never_trained_on_and_the_manifest_says_who_discarded_it(store):
    from server.labels import LabelChange, set_label

    sessions, data_dir, parent = store
    with sessions() as s:
        ids = {Path(seg.path).stem: seg.id for seg in s.scalars(select(SegmentRecord))}
    set_label(sessions, ids["good-2"], "alice", LabelChange(label="bad", note="fumbled the grasp"))
    set_label(sessions, ids["good-2"], "bob", LabelChange(discarded=True))  # who: the last to change it
    set_label(sessions, ids["good-1"], "alice", LabelChange(label="good"))
    lines = []
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lines.append)
    [summary] = runner.run(JobRequest(policy="lift-cube", config=TINY))
    assert summary["status"] == "succeeded", summary
    with sessions() as s:
        job = s.get(FinetuneJob, summary["job"])
        discarded = s.get(SegmentRecord, ids["good-2"])
    assert job.data["counts"]["segments"] == 1 and job.data["counts"]["excluded"] == 1
    why = job.data["excluded"]["good-2.mcap"]
    assert why.startswith("discarded by bob at ") and discarded.labelled_at.isoformat(timespec="seconds") in why
    assert any("left out segment good-2.mcap: discarded by bob" in line for line in lines)
    child = registry.resolve(sessions, summary["version"])
    assert child.manifest["segment_ids"] == [ids["good-1"]]
    assert child.manifest["excluded_segment_ids"] == [ids["good-2"]]
    assert child.manifest["labels"] == {str(ids["good-1"]): "good"}  # the verdicts on what it learned from
    assert (data_dir / "segments" / "good-2.mcap").is_file()  # discarded, not deleted
    # a discarded takeover is not news: it starts no nightly job
    write_segment(data_dir / "segments" / "later.mcap", make_task(TASK).obs_spec.dim, seed=9)
    with sessions() as s:
        later = _closed_segment("later", parent.id, datetime.now(UTC))
        s.add(later)
        s.commit()
        later_id = later.id
    set_label(sessions, later_id, "alice", LabelChange(discarded=True))
    assert runner.plan(JobRequest(config=TINY)) == []


def test_a_discard_made_while_a_job_is_planned_still_applies(store):
    """The selection reads the flag when the job loads its data, not from the rows it was planned with."""
    from server.finetune.plan import select_segments
    from server.labels import LabelChange, set_label
    from storage.takeovers import TakeoverSelection

    sessions, _, _ = store
    with sessions() as s:
        planned = list(s.scalars(select(SegmentRecord).where(SegmentRecord.status == "closed")))
    set_label(sessions, planned[0].id, "carol", LabelChange(discarded=True))
    kept, left_out, waiting = select_segments(sessions, planned, TakeoverSelection())
    assert [s.id for s in kept] == [s.id for s in planned[1:]] and not waiting
    assert list(left_out) == [planned[0].id] and left_out[planned[0].id].startswith("discarded by carol")


def test_since_parses_durations():
    assert parse_since("24h") == timedelta(hours=24) and parse_since("30m") == timedelta(minutes=30)
    assert parse_since("7d") == timedelta(days=7)
    for bad in ("", "24", "h", "-1h", "0h", "1y"):
        with pytest.raises(ValueError, match="--since"):
            parse_since(bad)


def test_job_summary_is_json(store):
    sessions, data_dir, _ = store
    lines = []
    FinetuneRunner(sessions, data_dir, progress=False, report=lines.append).run(
        JobRequest(policy="lift-cube", config=TINY)
    )
    doc = json.loads(lines[-1])
    assert doc["lineage"] == "lift-cube" and doc["data"]["segments"] == 2


@pytest.mark.parametrize("better", [True, False])
def test_the_gate_promotes_a_better_candidate_and_keeps_a_worse_one(store, monkeypatch, better):
    """Evaluation replaced by fixed results, so both of the gate's outcomes run end to end."""
    from policy.finetune import TaskResult
    from server.finetune import stages

    sessions, data_dir, parent = store
    calls = []

    def fake_evaluate(policy, tasks, episodes, seed, progress=True):
        calls.append(tasks)
        first = len(calls) == 1  # the parent is evaluated first, then the candidate
        nut = 2 if first else (8 if better else 1)
        return {t: TaskResult(t, 10, 9 if t == TASK else nut, seed) for t in tasks}

    monkeypatch.setattr(stages, "evaluate", fake_evaluate)
    [summary] = FinetuneRunner(sessions, data_dir, progress=False).run(JobRequest(policy="lift-cube", config=TINY))
    child = registry.resolve(sessions, summary["version"])
    rows = {r.ref: r for r in registry.versions(sessions, "lift-cube")}
    assert summary["promoted"] is better and calls == [["lift-cube", "lift-nut"]] * 2
    if better:
        assert child.status == "active" and rows["lift-cube@1"].status == "retired"
        assert child.status_reason == "gate passed: lift-nut 0.20 -> 0.80; lift-cube 0.90 -> 0.90 (tolerance 0.05)"
    else:
        assert child.status == "candidate" and rows["lift-cube@1"].status == "active"
        assert child.status_reason == "gate refused: not better on lift-nut: 0.10 against 0.20"
    with sessions() as s:
        job = s.scalars(select(FinetuneJob)).one()
    assert job.gate["promoted"] is better and job.gate["evidence"]["target_success"]["parent"] == 0.2
    # the parent's results are kept in its row, for the next job on the same seeds
    assert registry.by_id(sessions, parent.id).evaluation["tasks"]["lift-nut"]["successes"] == 2


def test_a_queued_job_whose_process_dies_before_starting_is_marked_failed(store):
    """The API queues a row, then starts a process; one that exits before taking the row leaves it failed
    with the exit code and its log, not queued forever."""
    import threading

    from server.db import utcnow
    from server.finetune.scheduler import JobLauncher
    from server.settings import FinetuneSettings

    sessions, data_dir, parent = store
    with sessions() as s:
        row = FinetuneJob(lineage="lift-cube", status="queued", trigger="api", parent_id=parent.id, created_at=utcnow())
        s.add(row)
        s.commit()
    runner = FinetuneRunner(sessions, data_dir, progress=False)
    done = threading.Event()

    def exited(code, log_file):
        runner.fail_queued(row.id, f"the job process exited with code {code} before starting; see {log_file}")
        done.set()

    url = f"sqlite:///{data_dir / 'hitl.db'}"
    launcher = JobLauncher(data_dir, url, FinetuneSettings(schedule=None, niceness=0, idle_priority=False))
    proc = launcher.launch("api", "lift-cube", row.id, ["--no-such-flag"], on_exit=exited)
    assert proc is not None and done.wait(120)
    with sessions() as s:
        job = s.get(FinetuneJob, row.id)
    assert job.status == "failed" and "exited with code 2 before starting" in job.error
    log_file = job.error.rsplit("see ", 1)[1]
    assert "unrecognized arguments: --no-such-flag" in Path(log_file).read_text()


def test_a_job_on_a_fresh_machine_records_the_parents_pretraining_data_from_its_recipe(store, monkeypatch):
    """The demo's nightly job on a clone without data/: the parent's config.json names its pretraining
    folder relative to the data root and the recipe that recorded it; the job records it, then trains."""
    sessions, data_dir, parent = store
    root = data_dir.parent / "clone"
    root.mkdir()
    monkeypatch.setenv("HITL_DATA_ROOT", str(root))
    config = Path(parent.path) / "config.json"
    info = json.loads(config.read_text())
    info["dataset"] = {
        "folder": "data/demos/lift-cube-dart",
        "train_episodes": [f"lift-cube_seed{i:06d}.mcap" for i in range(2)],
        "val_episodes": ["lift-cube_seed000002.mcap"],
        "recipe": {"task": TASK, "episodes": 3, "seed": 0, "pos_noise": 0.01, "rot_noise": 0.15},
    }
    config.write_text(json.dumps(info))
    lines = []
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lines.append)
    [summary] = runner.run(JobRequest(policy="lift-cube@active", config=TINY))
    assert summary["status"] == "succeeded", summary
    recorded = root / "data" / "demos" / "lift-cube-dart"
    assert sorted(p.name for p in recorded.glob("*.mcap")) == [f"lift-cube_seed{i:06d}.mcap" for i in range(3)]
    assert any("recording 3 of the 3 pretraining episodes" in line for line in lines), lines
    child = registry.resolve(sessions, summary["version"])
    child_info = read_info(child.path)
    # the child names the same folder, relative, and the recipe, so that the next night finds it too
    assert child_info["dataset"]["folder"] == "data/demos/lift-cube-dart"
    assert child_info["dataset"]["recipe"] == info["dataset"]["recipe"]
    assert child.manifest["pretraining"]["episodes"] == info["dataset"]["train_episodes"]


def test_a_parent_without_data_or_recipe_fails_and_says_how_to_get_the_data(store, monkeypatch):
    sessions, data_dir, parent = store
    monkeypatch.setenv("HITL_DATA_ROOT", str(data_dir.parent / "elsewhere"))
    config = Path(parent.path) / "config.json"
    info = json.loads(config.read_text())
    info["dataset"]["folder"] = "data/demos/missing"
    config.write_text(json.dumps(info))
    runner = FinetuneRunner(sessions, data_dir, progress=False, report=lambda _: None)
    [summary] = runner.run(JobRequest(policy="lift-cube@active", config=TINY))
    assert summary["status"] == "failed" and "holds no recipe" in summary["error"], summary
    assert "--pretrain-data" in summary["error"]

"""The fleet on in-process workers and a kinematic stand-in task: fast, no uvicorn, no sleeps.
Ticks are driven by hand, so every assertion is about one known sequence of ticks."""

from dataclasses import FrozenInstanceError
from datetime import UTC, datetime

import numpy as np
import pytest
from sqlalchemy import select

from lab.assisted import AssistConfig, run_assisted
from policy.evaluate import rollout_policy
from server.db import EpisodeRecord, PolicyVersion, make_engine, migrate, session_factory
from server.errors import ServiceError
from server.fleet.fleet import Fleet
from server.settings import RobotGroup, Settings
from server.workers import InProcessWorker, Priority, in_process_workers
from sim.registry import make_task
from sim.spaces import TeleopCommand
from tests.helpers import KinematicTask, tiny_policy_folder


class Recorded(InProcessWorker):
    """An in-process worker that remembers what it was asked and its priority hints."""

    def __init__(self, task):
        super().__init__(task)
        self.actions, self.priority = [], None

    def request_step(self, action, hold=False):
        self.actions.append(np.array(action))
        super().request_step(action, hold)

    def prioritize(self, priority):
        self.priority = priority
        return True


def _fleet(tmp_path, threshold=-1.0, horizon=1000, count=1, factory=None, success_z=None, **settings):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold)
    s = Settings(
        data_dir=tmp_path / "var",
        robots=[RobotGroup(task="lift-cube", count=count, policy=policy)],
        inference={"trace_policies": False},
        **settings,
    )
    migrate(s.db_url)
    made = []

    def make(robot_id, task, images=False):
        made.append(Recorded(KinematicTask(horizon, success_z)))
        return made[-1]

    fleet = Fleet(s, session_factory(make_engine(s.db_url)), factory or make)
    fleet.spawn_workers()  # start the workers without the loop thread: ticks by hand
    return fleet, made


UP = TeleopCommand((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), 1.0)


def test_commands_between_ticks_are_applied_once_in_order_or_refused(tmp_path):
    fleet, workers = _fleet(tmp_path)
    fleet.tick()  # threshold -1: the robot asks at once and holds
    assert fleet.view(0).mode == "waiting" and fleet.queue.get(0) is not None
    fleet.claim(0, "op")
    # the lease is the operator's at once; the next tick (driven here by hand) puts the robot under their control
    assert fleet.view(0).mode == "waiting" and fleet.queue.get(0).holder == "op"
    assert workers[0].priority == Priority.BACKGROUND
    fleet.tick()  # no command yet: it holds
    assert fleet.view(0).mode == "teleop"
    assert workers[0].priority == Priority.CONTROL  # the operator's robot runs at the loop's priority
    z0 = fleet.view(0).frame.pos[2]
    turn = TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.1), 1.0)
    # a stream faster than the control rate: three commands before one tick
    assert [fleet.command(0, "op", c) for c in (UP, turn, UP)] == [1, 2, 3]
    with pytest.raises(ServiceError) as too_much:
        fleet.command(0, "op", TeleopCommand((0.0, 0.0, 0.02), (0.0, 0.0, 0.0), 1.0))
    assert too_much.value.status == 429 and "per-step limits" in str(too_much.value)
    before = len(workers[0].actions)
    fleet.tick()
    sent = workers[0].actions[before:]
    assert len(sent) == 1  # the three accepted commands, composed into one step, applied once
    np.testing.assert_allclose(sent[0][2], z0 + 0.02, atol=1e-9)
    assert fleet.view(0).assisted_steps == 1
    fleet.tick()  # nothing new: the robot holds the composed target, no command is replayed
    np.testing.assert_allclose(workers[0].actions[-1], sent[0])
    assert fleet.view(0).assisted_steps == 1
    with pytest.raises(ServiceError) as not_holder:
        fleet.command(0, "someone-else", UP)
    assert not_holder.value.status == 409
    fleet.stop()


def test_budgeted_takeover_hands_back_and_a_lease_expiry_requeues(tmp_path):
    fleet, workers = _fleet(tmp_path, controller={"budget": 2}, queue={"lease_seconds": 0.05}, count=2)
    fleet.tick()
    fleet.claim(0, "op")
    for _ in range(2):
        fleet.command(0, "op", UP)
        fleet.tick()
    assert fleet.view(0).mode in ("autonomous", "waiting")  # handed back (and, at threshold -1, asks again)
    assert fleet.view(0).assisted_steps == 2 and workers[0].priority is not None
    fleet.claim(1, "op")
    import time

    time.sleep(0.1)
    fleet.tick()
    assert fleet.view(1).mode == "waiting" and fleet.queue.get(1).holder is None
    with pytest.raises(ServiceError) as gone:
        fleet.command(1, "op", UP)
    assert gone.value.status == 409
    fleet.stop()


def test_autonomous_robots_are_not_commandable_and_unknown_robots_are_404(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9)
    fleet.tick()
    with pytest.raises(ServiceError) as auto:
        fleet.command(0, "op", UP)
    assert auto.value.status == 409
    with pytest.raises(ServiceError) as missing:
        fleet.command(5, "op", UP)
    assert missing.value.status == 404
    fleet.stop()


def test_a_new_policy_version_takes_over_at_the_next_episode(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=4)
    fleet.tick()
    old = fleet.view(0).slot.version
    episode = fleet.view(0).episode_id
    other = tiny_policy_folder(tmp_path / "policy-v2", "lift-cube", 1e9)
    version = fleet.register_policy(other, parent=old)
    with fleet.sessions() as s:
        assert s.get(PolicyVersion, version).status == "candidate"
    fleet.activate_policy(version)
    fleet.tick()
    assert fleet.view(0).slot.version == old and fleet.view(0).episode_id == episode  # finishes its episode
    for _ in range(6):
        fleet.tick()
    assert fleet.view(0).episode_id != episode and fleet.view(0).slot.version == version
    with fleet.sessions() as s:
        assert s.get(PolicyVersion, version).status == "active" and s.get(PolicyVersion, version).parent_id == old
        assert s.get(PolicyVersion, old).status == "retired"
    with pytest.raises(ServiceError) as missing:
        fleet.activate_policy(999)
    assert missing.value.status == 404
    with pytest.raises(ServiceError) as nowhere:
        fleet.register_policy(tmp_path / "nowhere")
    assert nowhere.value.status == 404  # no policy there
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "config.json").write_text("{not json")
    with pytest.raises(ServiceError) as broken:
        fleet.register_policy(tmp_path / "broken")
    assert broken.value.status == 422  # a policy folder that cannot be read
    fleet.stop()


def test_a_version_that_cannot_run_its_task_is_not_registered_and_the_message_names_the_channels(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9)
    cup = tiny_policy_folder(tmp_path / "cup", "cup-stack", 1e9, obs_labels=make_task("cup-stack").obs_spec.labels())
    with pytest.raises(ServiceError) as err:
        fleet.register_policy(cup, task="lift-cube")
    assert err.value.status == 409  # the request conflicts with what the folder holds
    assert "cannot run task lift-cube: it was trained on observations [eef_pos(3)" in err.value.message
    assert "missing green_pos, green_rot6d" in err.value.message and "extra object_pos" in err.value.message
    with fleet.sessions() as s:
        assert [v.path for v in s.scalars(select(PolicyVersion))] == [str((tmp_path / "policy").resolve())]
    fleet.stop()


def test_metrics_aggregate_finished_episodes(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=3, count=2)
    for _ in range(10):
        fleet.tick()
    m = fleet.metrics()
    assert m.episodes >= 4 and m.success_rate == 0.0 and m.robots_by_mode["autonomous"] == 2
    # the totals are kept between episodes (no query per metrics request), and renewed at each episode's end
    with fleet.recorder.sessions() as s:  # a row the fleet did not write: not seen until the fleet's next episode ends
        s.add(EpisodeRecord(robot_id=9, task="lift-cube", seed=0, outcome="success", steps=1, assisted_steps=0,
                            assistance_events=0, started_at=datetime.now(UTC)))  # fmt: skip
        s.commit()
    assert fleet.metrics().episodes == m.episodes
    with pytest.raises(FrozenInstanceError):  # the kept totals are not the caller's to change
        fleet.recorder.totals().episodes = -1
    for _ in range(4):
        fleet.tick()
    after = fleet.metrics()
    assert after.episodes >= m.episodes + 2 and after.success_rate > 0.0  # renewed, with that row
    fleet.stop()


def test_metrics_report_the_longest_wait_to_a_claim_and_the_oldest_unclaimed_request(tmp_path):
    fleet, _ = _fleet(tmp_path, count=2)
    fleet.tick()  # threshold -1: both robots ask at once
    m = fleet.metrics()
    assert m.queue_wait_max_s is None and m.queue_oldest_unclaimed_s >= 0
    fleet.claim(0, "op")
    import time

    before = time.monotonic()
    m = fleet.metrics()
    assert m.queue_wait_max_s == fleet.queue.waits[0] >= 0
    assert m.queue_oldest_unclaimed_s >= before - fleet.queue.get(1).created  # robot 1 still waits
    fleet.stop()


def test_served_evaluated_and_assisted_episodes_take_the_same_actions(tmp_path):
    """The fleet (real simulator, in-process workers), ``hitl rollout``'s loop and ``hitl assist``'s
    loop, same seeds and settings, send the same actions: one controller."""
    fleet, _ = _fleet(tmp_path, threshold=1e9, count=2, factory=_recording_real_workers())
    workers = [fleet.robots[i].worker for i in (0, 1)]
    seeds = [fleet.robots[i].seed for i in (0, 1)]
    episodes = [fleet.view(i).episode_id for i in (0, 1)]
    for _ in range(40):
        fleet.tick()
    assert [fleet.view(i).episode_id for i in (0, 1)] == episodes  # still the first episodes
    fleet.stop()
    policy = fleet.robots[0].slot.policy
    evaluated, _ = rollout_policy(policy, "lift-cube", seeds, n_envs=2, trace=True, progress=False)
    driver = fleet.robots[0].slot.controller.signals["denoising"]  # calibrated at 1e9: never asks
    assisted, _ = run_assisted(policy, "lift-cube", seeds, driver, config=AssistConfig(n_envs=2), progress=False)
    for worker, ep, helped in zip(workers, evaluated, assisted, strict=True):
        served = np.stack(worker.actions[:30])
        assert len(ep.trace) >= 30 and helped.events == 0
        np.testing.assert_allclose(served, np.stack([t[2] for t in ep.trace[:30]]), rtol=0, atol=1e-5)
        np.testing.assert_allclose(served, np.stack(helped.actions[:30]), rtol=0, atol=1e-5)


def _recording_real_workers():
    real = in_process_workers()

    def factory(robot_id, task, images=False):
        worker = real(robot_id, task, images)
        sent = []
        step = worker.request_step

        def request_step(action, hold=False):
            sent.append(np.array(action))
            step(action, hold)

        worker.request_step, worker.actions = request_step, sent
        return worker

    return factory


def _segments(fleet):
    from server.db import SegmentRecord

    with fleet.sessions() as s:
        return s.query(SegmentRecord).order_by(SegmentRecord.id).all()


def _episodes(fleet):
    from server.db import EpisodeRecord

    with fleet.sessions() as s:
        return s.query(EpisodeRecord).order_by(EpisodeRecord.id).all()


def test_waiting_does_not_use_up_the_horizon_and_a_timeout_waits_for_the_hand_back(tmp_path):
    fleet, workers = _fleet(tmp_path, horizon=5, controller={"hand_back": "continuous", "return_after": 1000})
    for _ in range(30):  # asks at once, then waits six horizons' worth of ticks for an operator
        fleet.tick()
    robot = fleet.view(0)
    assert robot.mode == "waiting" and robot.episodes_done == 0
    assert robot.frame.t == 29 and robot.frame.clock == 0  # the physics held 29 steps; the clock did not run
    fleet.claim(0, "op")
    for _ in range(8):  # the operator drives past the horizon: the episode does not end under their hands
        fleet.command(0, "op", UP)
        fleet.tick()
    robot = fleet.view(0)
    assert robot.mode == "teleop" and robot.episodes_done == 0 and robot.frame.clock >= 5
    fleet.release(0, "op")
    fleet.tick()  # the first frame after the hand-back ends the episode as the timeout it was
    assert fleet.view(0).episodes_done == 1
    [segment] = _segments(fleet)
    assert segment.status == "closed" and segment.ended_by == "hand-back" and segment.steps == 8
    first = _episodes(fleet)[0]
    assert first.outcome == "timeout" and first.steps == 8 and first.assisted_steps == 8  # only counted steps


def test_a_takeover_ends_with_the_episode_only_at_success_or_with_the_lease(tmp_path):
    fleet, _ = _fleet(tmp_path, horizon=3, success_z=1.05, controller={"hand_back": "continuous", "return_after": 1000})
    fleet.tick()
    fleet.claim(0, "op")
    fleet.tick()  # the claim applies; no command yet: the robot holds (holds do not use up the horizon)
    for _ in range(5):  # z climbs 1 cm a step from 1.0: past the horizon (3), then at 1.05 success
        assert fleet.view(0).mode == "teleop"
        fleet.command(0, "op", UP)
        fleet.tick()
    fleet.tick()
    assert fleet.view(0).episodes_done == 1 and fleet.view(0).successes == 1
    [segment] = _segments(fleet)
    assert segment.ended_by == "episode-ended" and segment.steps == 5
    assert _episodes(fleet)[0].outcome == "success"

    # a lease that runs out past the horizon: the request goes back to the queue, and the episode ends
    lapsed, _ = _fleet(
        tmp_path / "lease", horizon=2, queue={"lease_seconds": 0.05}, controller={"hand_back": "continuous"}
    )
    lapsed.tick()
    lapsed.claim(0, "op")
    for _ in range(3):
        lapsed.command(0, "op", TeleopCommand((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), -1.0))
        lapsed.tick()
    assert lapsed.view(0).mode == "teleop" and lapsed.view(0).episodes_done == 0
    import time

    time.sleep(0.1)
    lapsed.tick()  # the lease expired: the robot holds, its segment closes
    lapsed.tick()  # the frame after that hold ends the timed-out episode
    assert lapsed.view(0).episodes_done == 1 and _episodes(lapsed)[0].outcome == "timeout"
    assert [s.ended_by for s in _segments(lapsed)] == ["lease-expired"]


def test_a_cooldown_after_the_hand_back_keeps_a_robot_from_flooding_the_queue(tmp_path):
    fleet, _ = _fleet(tmp_path, controller={"budget": 2, "cooldown": 3})  # threshold -1: always wants help
    fleet.tick()
    fleet.claim(0, "op")
    for _ in range(2):
        fleet.command(0, "op", UP)
        fleet.tick()
    assert fleet.view(0).mode == "autonomous"  # the budget is spent: control is back
    modes = []
    for _ in range(5):
        fleet.tick()
        modes.append(fleet.view(0).mode)
    # three policy steps without a request, then it asks again
    assert modes == ["autonomous", "autonomous", "autonomous", "waiting", "waiting"]


def test_the_watchdog_asks_once_when_an_episode_runs_long(tmp_path):
    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=10, controller={"watchdog": 0.5, "budget": 1, "cooldown": 0})
    modes = []
    for _ in range(6):  # the signal never asks; five policy steps are half the horizon
        fleet.tick()
        modes.append(fleet.view(0).mode)
    assert modes == ["autonomous"] * 5 + ["waiting"]
    assert fleet.queue.get(0).reason == "watchdog: 5 of 10 steps without success"
    fleet.claim(0, "op")
    fleet.command(0, "op", UP)
    fleet.tick()
    assert fleet.view(0).mode == "autonomous"  # the budget of one step is spent
    for _ in range(3):  # once per episode: it does not ask again
        fleet.tick()
        assert fleet.view(0).mode == "autonomous"


def test_an_accepted_command_renews_the_lease(tmp_path):
    import time

    fleet, _ = _fleet(tmp_path, queue={"lease_seconds": 0.3}, controller={"hand_back": "continuous"})
    fleet.tick()
    fleet.claim(0, "op")
    for _ in range(6):  # 0.6 s of driving, two leases' worth, with no heartbeat
        fleet.command(0, "op", UP)
        fleet.tick()
        time.sleep(0.1)
    assert fleet.view(0).mode == "teleop" and fleet.queue.get(0).holder == "op"
    time.sleep(0.4)  # then silence: the lease runs out
    fleet.tick()
    assert fleet.view(0).mode == "waiting" and fleet.queue.get(0).holder is None


def test_a_worker_that_dies_while_a_step_is_sent_faults_alone_and_the_fleet_runs_on(tmp_path):
    from server.workers import WorkerFault

    fleet, workers = _fleet(tmp_path, threshold=1e9, count=2, controller={"cooldown": 0})
    fleet.tick()

    def dead(action, hold=False):
        raise WorkerFault("worker pipe broke: gone")

    workers[0].request_step = dead
    for _ in range(3):
        fleet.tick()  # no tick fails: robot 0 faults, robot 1 keeps stepping
    assert fleet.view(0).mode == "faulted" and fleet.robots[0].worker is None
    steps = fleet.view(1).frame.t
    fleet.tick()
    assert fleet.view(1).mode == "autonomous" and fleet.view(1).frame.t == steps + 1


def test_a_lease_that_runs_out_while_paused_ends_that_takeover(tmp_path):
    import time

    fleet, _ = _fleet(tmp_path, queue={"lease_seconds": 0.05}, controller={"hand_back": "continuous"})
    fleet.tick()
    fleet.claim(0, "alice")
    fleet.command(0, "alice", UP)
    fleet.tick()
    fleet.pause(0)
    time.sleep(0.1)
    fleet.tick()  # the lease ran out while the robot was paused
    fleet.resume(0)
    assert fleet.view(0).mode == "waiting"
    fleet.claim(0, "bob")
    fleet.command(0, "bob", UP)
    fleet.tick()
    rows = _segments(fleet)
    assert [(r.operator, r.ended_by) for r in rows] == [("alice", "lease-expired"), ("bob", None)]


def test_freeze_idle_steps_a_waiting_or_idle_teleop_robot_only_on_its_operators_commands(tmp_path):
    """With ``freeze_idle`` the scene of a robot that waits for its operator (or for the next command)
    waits too: the asking step's hold is the only hold it gets, so its numbers do not depend on latency."""
    fleet, workers = _fleet(tmp_path, workers={"freeze_idle": True}, controller={"budget": 2, "cooldown": 0})
    fleet.tick()  # threshold -1: the robot asks at once; that step's hold is sent
    assert fleet.view(0).mode == "waiting" and len(workers[0].actions) == 1
    clock = fleet.view(0).frame.clock
    for _ in range(3):  # nobody has claimed it: not stepped, its frame stays the current one
        fleet.tick()
    assert len(workers[0].actions) == 1 and fleet.view(0).frame.clock == clock
    fleet.claim(0, "op")
    fleet.tick()  # under teleop without a command: still not stepped
    assert len(workers[0].actions) == 1
    fleet.command(0, "op", UP)
    fleet.tick()
    assert len(workers[0].actions) == 2 and fleet.view(0).assisted_steps == 1
    fleet.stop()


def test_claims_and_releases_never_wait_for_a_tick_in_progress(tmp_path):
    """A tick holds the fleet lock for its whole batch; a claim and a release are decided by the queue
    at once and applied by the loop at its next tick (``server.fleet.inbox``), which the view then shows."""
    import threading
    import time

    fleet, workers = _fleet(tmp_path, controller={"hand_back": "continuous", "return_after": 1000})
    fleet.tick()  # threshold -1: the robot asks
    in_tick, done = threading.Event(), threading.Event()

    def long_tick():
        with fleet.lock:
            in_tick.set()
            done.wait(10)

    t = threading.Thread(target=long_tick)
    t.start()
    assert in_tick.wait(5)
    try:
        t0 = time.monotonic()
        fleet.claim(0, "op")  # would wait 10 s for the lock held by the "tick"
        assert time.monotonic() - t0 < 2.0
        assert fleet.view(0).mode == "waiting" and fleet.queue.get(0).holder == "op"
        assert fleet.command(0, "op", UP) == 1  # the claimant's command waits for the tick that applies the claim
        with pytest.raises(ServiceError) as other:
            fleet.claim(0, "bob")
        assert other.value.status == 409
        assert not done.is_set()
    finally:
        done.set()
        t.join()
    before = len(workers[0].actions)
    fleet.tick()  # applies the claim, then steps the robot on the command
    robot = fleet.view(0)
    assert robot.mode == "teleop" and robot.assisted_steps == 1 and len(workers[0].actions) == before + 1
    [segment] = _segments(fleet)
    assert segment.operator == "op" and segment.status == "open"

    with fleet.lock:  # a release during a tick: the operator's commands refused from then on
        fleet.release(0, "op")
        assert fleet.view(0).mode == "teleop"  # until the next tick hands the robot back
        with pytest.raises(ServiceError) as refused:
            fleet.command(0, "op", UP)
        assert refused.value.status == 409
    fleet.tick()
    assert fleet.view(0).mode in ("autonomous", "waiting")  # handed back (and, at threshold -1, asks again)
    req = fleet.queue.get(0)
    assert req is None or req.holder is None
    [segment] = _segments(fleet)
    assert segment.ended_by == "hand-back" and segment.steps == 1


def test_a_claim_whose_request_ends_before_the_next_tick_changes_nothing(tmp_path):
    fleet, _ = _fleet(tmp_path, queue={"lease_seconds": 0.05}, controller={"hand_back": "continuous"})
    fleet.tick()
    fleet.claim(0, "op")
    import time

    time.sleep(0.1)  # the lease runs out before the loop applies the claim
    fleet.tick()
    robot = fleet.view(0)
    assert robot.mode == "waiting" and fleet.queue.get(0).holder is None
    assert _segments(fleet) == []  # no takeover began
    with pytest.raises(ServiceError) as gone:
        fleet.command(0, "op", UP)
    assert gone.value.status == 409


def test_a_waiting_robot_shows_the_request_the_queue_holds_and_its_takeover_records_it(tmp_path):
    """The robot's asking numbers are its request's, the queue's own (not the paper's U and threshold);
    the takeover answering it records them; once handed back the robot shows the live score again."""
    from server.api.assistance import request_out
    from server.api.robots import detail, summary
    from server.db import SegmentRecord
    from storage.paths import in_store
    from storage.segments import read_segment

    fleet, _ = _fleet(tmp_path, controller={"budget": 2})
    fleet.tick()  # threshold -1: choice-stall (threshold 1) asks at once
    view, req = fleet.view(0), fleet.queue.get(0)
    assert view.mode == "waiting" and view.ask == req.ask
    out, queued = summary(view), request_out(req)
    assert (out.asking.score, out.asking.threshold, out.asking.reason) == (
        queued.score,
        queued.threshold,
        queued.reason,
    )
    assert (out.uncertainty, out.threshold) == (queued.score, queued.threshold) == (queued.score, 1.0)
    assert out.asking.signal == queued.signal == "choice-stall" and out.asking.wants_help is True
    assert out.asking.asked_at_step == view.frame.clock and queued.reason.startswith("choice-stall: ")
    # the paper's metric is a field of its own: its U and the denoising threshold (-1), not the asking signal's
    assert out.paper.threshold == -1.0 and out.paper.U == view.u_history[-1] == req.paper_u
    history = detail(view)
    assert len(history.score_history) == len(history.u_history) == 1 and history.score_history == [queued.score]

    fleet.claim(0, "op")
    fleet.command(0, "op", UP)
    fleet.tick()  # the claim applies, one operator step
    teleop = summary(fleet.view(0))
    assert fleet.view(0).mode == "teleop" and teleop.asking.reason == queued.reason  # still the request's
    assert teleop.uncertainty == queued.score  # the score it asked with, not the operator step's
    fleet.release(0, "op")
    assert fleet.view(0).mode == "teleop"  # the next tick hands it back
    fleet.tick()
    assert fleet.view(0).mode in ("autonomous", "waiting")  # handed back (and it may ask again)
    with fleet.sessions() as s:
        [row] = s.scalars(select(SegmentRecord)).all()
    assert (row.signal, row.score, row.threshold, row.reason, row.paper_u) == (
        "choice-stall",
        req.score,
        req.threshold,
        req.reason,
        req.paper_u,
    )
    segment = read_segment(in_store(fleet.data_dir, row.path))
    assert segment.request == {
        "signal": "choice-stall",
        "score": req.score,
        "threshold": 1.0,
        "reason": req.reason,
        "asked_at_step": req.asked_at_step,
        "paper_u": req.paper_u,
    }
    assert (segment.meta["signal"], segment.meta["threshold"]) == ("choice-stall", 1.0)  # whose score steps hold
    fleet.stop()


def test_the_watchdogs_and_a_requested_help_show_as_the_queue_ranks_them(tmp_path):
    from server.api.robots import summary

    fleet, _ = _fleet(tmp_path, threshold=1e9, horizon=10, controller={"watchdog": 0.5, "budget": 1})
    fleet.tick()
    # a robot that has not asked shows the asking signal's latest score and threshold, and no reason
    live = summary(fleet.view(0)).asking
    assert live.signal == "choice-stall" and live.reason is None and live.asked_at_step is None
    assert live.score == fleet.view(0).scores["choice-stall"] and live.threshold == 1.0 and live.wants_help is False
    for _ in range(5):
        fleet.tick()
    req = fleet.queue.get(0)
    asking = summary(fleet.view(0)).asking
    assert (asking.signal, asking.score, asking.threshold, asking.reason, asking.wants_help) == (
        "watchdog",
        req.score,
        req.threshold,
        "watchdog: 5 of 10 steps without success",
        None,
    )
    assert (req.score, req.threshold, asking.asked_at_step) == (1.0, 1.0, 5)
    fleet.claim(0, "op")
    fleet.command(0, "op", UP)
    fleet.tick()  # the budget of one step: handed back
    assert fleet.view(0).mode == "autonomous" and fleet.view(0).ask is None
    fleet.request_help(0, "drill")
    drill = summary(fleet.view(0)).asking
    assert (drill.signal, drill.score, drill.threshold, drill.reason) == (None, 1.0, 1.0, "drill")
    assert fleet.queue.get(0).ask == fleet.view(0).ask
    fleet.stop()


def test_camera_views_shown_during_a_takeover_are_recorded_in_its_segment(tmp_path):
    """The views the feed renders while a robot is under teleop go into its open takeover file; outside a
    takeover there is no file to write them to, and nothing is written."""
    import io
    import time as clock

    from PIL import Image

    from server.cameras import CameraImages
    from storage.segments import read_segment

    fleet, _ = _fleet(tmp_path)
    jpeg = io.BytesIO()
    Image.fromarray(np.zeros((12, 16, 3), np.uint8)).save(jpeg, format="JPEG")
    views = lambda t: CameraImages(0, t, t, {"front": jpeg.getvalue(), "wrist": jpeg.getvalue()}, 16, 12, clock.time())  # noqa: E731
    fleet.tick()
    fleet.cameras.on_images(views(0))  # waiting, no takeover: nowhere to write
    fleet.claim(0, "op")
    fleet.command(0, "op", UP)
    fleet.tick()
    fleet.cameras.on_images(views(1))
    fleet.cameras.on_images(views(2))
    fleet.release(0, "op")
    fleet.tick()
    [segment] = _segments(fleet)
    seg = read_segment(fleet.settings.data_dir / segment.path)
    assert [m["frame_id"] for m in seg.images["front"]] == ["step-1", "step-2"] and len(seg.images["wrist"]) == 2
    assert seg.jpeg(seg.images["wrist"][0]) == jpeg.getvalue()
    fleet.stop()


def test_a_served_robots_control_state_has_one_writer_the_control_loop(tmp_path):
    """While the loop thread runs, it alone changes a robot's mode and counters: claims, releases and an
    admin's actions reach the robot through its inbox, and a change from any other thread is refused."""
    import threading
    import time

    from policy.hitl_state import WrongWriter

    fleet, _ = _fleet(tmp_path, controller={"hand_back": "continuous", "return_after": 1000}, control_hz=100)
    stop = threading.Event()
    loop = threading.Thread(target=fleet.loop.run, args=(stop,), daemon=True)
    loop.start()

    def until(mode):
        deadline = time.monotonic() + 10
        while fleet.view(0).mode != mode and time.monotonic() < deadline:
            time.sleep(0.01)
        return fleet.view(0).mode

    try:
        assert until("waiting") == "waiting"  # threshold -1: the robot asks
        control = fleet.robots[0].control
        with pytest.raises(WrongWriter):
            control.take_over(None)  # not the loop's thread: refused, nothing changed
        with pytest.raises(WrongWriter):
            fleet.robots[0].slot.controller.release(0)
        assert control.mode == "waiting"
        fleet.claim(0, "op")
        assert until("teleop") == "teleop"  # the loop applied the claim
        fleet.pause(0)  # an admin's action returns once the loop has applied it
        assert fleet.view(0).mode == "paused" and control.paused_from == "teleop"
        with pytest.raises(ServiceError) as twice:
            fleet.resume(0)
            fleet.resume(0)  # the loop's refusal reaches the caller
        assert twice.value.status == 409 and "not paused" in str(twice.value)
        assert fleet.view(0).mode == "teleop"
    finally:
        stop.set()
        loop.join(10)
    control.pause()  # no loop: unbound again
    fleet.stop()

"""The RobotWorker contract on every back end: reset, step, non-blocking poll, faults, priority."""

import os
import time

import numpy as np
import pytest

from server.settings import Settings
from server.workers import WORKERS, InProcessWorker, Priority, WorkerFault, wait_any
from server.workers.pool import PoolFactory
from server.workers.process import process_workers
from sim.frame import RobotFrame
from tests.helpers import KinematicTask


def _answer(worker, timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        wait_any([worker], 0.5)
        frame = worker.poll()
        if frame is not None:
            return frame
    raise AssertionError("no answer in time")


def _contract(worker):
    worker.request_reset(4)
    assert worker.busy
    first = _answer(worker)
    assert isinstance(first, RobotFrame) and first.t == 0 and not worker.busy
    assert worker.poll() is None  # an answer is returned once
    up = first.hold.copy()
    up[2] += 0.01
    worker.request_step(up)
    frame = _answer(worker)
    assert frame.t == 1 and frame.obs.shape == first.obs.shape
    worker.request_step(np.full(10, np.nan))  # a bad action is the robot's error, reported as a fault
    with pytest.raises(WorkerFault, match="non-finite"):
        _answer(worker)
    worker.kill()
    assert not worker.alive()
    with pytest.raises(WorkerFault):
        worker.poll()


def test_the_in_process_worker_keeps_the_contract():
    _contract(InProcessWorker(KinematicTask()))


def test_the_process_worker_keeps_the_contract_and_maps_priorities_to_niceness():
    worker = WORKERS["process"](Settings(workers={"kind": "process", "niceness": 7}))(3, "lift-cube")
    try:
        assert worker.name == "robot-3" and worker.pid != os.getpid()  # its own process
        assert worker.prioritize(Priority.BACKGROUND)
        assert os.getpriority(os.PRIO_PROCESS, worker.pid) == 7
        if worker.prioritize(Priority.CONTROL):  # raising a priority needs CAP_SYS_NICE
            assert os.getpriority(os.PRIO_PROCESS, worker.pid) == 0
        else:
            assert os.getpriority(os.PRIO_PROCESS, worker.pid) == 7
        _contract(worker)
    finally:
        worker.kill()
        worker.join(5)


def test_a_busy_process_worker_that_dies_faults_with_its_exit_code():
    worker = process_workers(7)(0, "lift-cube")
    try:
        worker.request_reset(1)
        hold = _answer(worker).hold
        worker.request_step(hold)
        os.kill(worker.pid, 9)  # dies with the step in flight
        with pytest.raises(WorkerFault, match="exited"):
            _answer(worker, timeout=10)
        assert not worker.alive()
    finally:
        worker.kill()
        worker.join(5)


def test_process_workers_isolate_each_robot_in_its_own_process():
    factory = process_workers(7)
    a, b, bad = factory(0, "lift-cube"), factory(1, "lift-cube"), factory(2, "no-such-task")
    try:
        assert len({a.pid, b.pid, bad.pid}) == 3  # a process per robot
        if a.prioritize(Priority.CONTROL):  # niceness is per robot: b stays in the background
            assert os.getpriority(os.PRIO_PROCESS, a.pid) == 0
        assert b.prioritize(Priority.BACKGROUND) and os.getpriority(os.PRIO_PROCESS, b.pid) == 7
        with pytest.raises(WorkerFault, match="exited|pipe broke"):  # a task that cannot be built: its robot alone
            bad.request_reset(1)
            _answer(bad, timeout=60)
        a.request_reset(1)
        b.request_reset(1)
        wait_any([a, b], 120.0, min_ready=2)
        fa, fb = a.poll(), b.poll()
        assert fa is not None and fb is not None
        a.request_step(fa.hold)  # in flight when a's process dies
        b.request_step(fb.hold)
        os.kill(a.pid, 9)
        with pytest.raises(WorkerFault, match="exited"):
            _answer(a, timeout=10)
        assert _answer(b).t == 1 and b.alive()  # b carries on
        b.request_step(fb.hold)
        pid = b.pid
        b.kill()  # killing a robot kills its process, even with a step in flight
        assert not b.alive()
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
        a.kill()
        again = factory(0, "lift-cube")  # the fleet's restart: a fresh process
        assert again.pid not in (a.pid, pid) and again.name == "robot-0"
        again.request_reset(1)
        assert _answer(again).t == 0
        again.close()
        again.join(5)
    finally:
        for w in (a, b, bad):
            w.close()
        for w in (a, b, bad):
            w.join(5)


def test_pool_workers_keep_the_contract_and_share_a_process():
    factory = WORKERS["pool"](Settings(workers={"kind": "pool", "niceness": 7, "robots_per_process": 2}))
    a, b, c = factory(0, "lift-cube"), factory(1, "lift-cube"), factory(2, "lift-cube")
    try:
        assert a.host is b.host and c.host is not a.host  # two robots per process
        assert a.prioritize(Priority.BACKGROUND)
        assert os.getpriority(os.PRIO_PROCESS, a.host.process.pid) == 7
        _contract(a)  # ends with a's error and kill: b, on the same process, carries on
        b.request_reset(3)
        c.request_reset(3)
        wait_any([b, c], 120.0, min_ready=2)
        fb, fc = b.poll(), c.poll()
        assert fb is not None and fc is not None and fb.t == 0
        np.testing.assert_allclose(fb.obs, fc.obs)  # same seed, same task: same frame
        # a robot restarted on the host gets its own answers, not its dropped predecessor's
        again = factory(0, "lift-cube")
        assert again.host is a.host
        again.request_reset(5)
        assert _answer(again).t == 0
    finally:
        for w in (a, b, c):
            w.close()
        for w in (a, b, c):
            w.join(5)


def test_a_pool_process_that_dies_faults_each_of_its_robots_and_new_robots_get_a_new_one():
    factory = PoolFactory(10, 4)
    a, b = factory(0, "lift-cube"), factory(1, "lift-cube")
    try:
        a.request_reset(1)
        b.request_reset(1)
        wait_any([a, b], 120.0, min_ready=2)
        assert a.poll() is not None and b.poll() is not None
        a.request_step(np.zeros(10))  # in flight when the process dies
        os.kill(a.host.process.pid, 9)
        with pytest.raises(WorkerFault, match="exited"):
            _answer(a, timeout=10)
        with pytest.raises(WorkerFault):
            b.poll()  # idle, but its process is gone
        a.kill()
        b.kill()
        fresh = factory(0, "lift-cube")
        assert fresh.host is not a.host and fresh.alive()
        fresh.request_reset(1)
        assert _answer(fresh).t == 0
        fresh.close()
        fresh.join(5)
    finally:
        a.kill()
        b.kill()


def test_a_pool_robot_whose_task_cannot_be_built_faults_alone():
    factory = PoolFactory(10, 4)
    bad, good = factory(0, "no-such-task"), factory(1, "lift-cube")
    try:
        bad.request_reset(1)
        with pytest.raises(WorkerFault, match="no-such-task"):
            _answer(bad, timeout=60)
        good.request_reset(1)
        assert _answer(good).t == 0
        good.prioritize(Priority.CONTROL)  # raising the niceness back needs CAP_SYS_NICE; the order does not
        assert good.host.control == {1}  # its requests now go first in the host
        assert good.pid == good.host.process.pid == bad.pid  # both robots' physics, in one process
        good.request_step(_answer_hold(good))
        assert _answer(good).t == 1
    finally:
        for w in (bad, good):
            w.close()
        good.join(5)


def _answer_hold(worker) -> np.ndarray:
    worker.request_reset(2)
    return _answer(worker).hold


def _actor_pid(worker) -> int:
    return worker.ray.get(worker.host.handle.pid.remote(), timeout=60)


def test_ray_workers_keep_the_contract_and_share_an_actor(ray_local):
    factory = WORKERS["ray"](Settings(workers={"kind": "ray", "robots_per_process": 2}, ray={"cpus_per_actor": 0.5}))
    a, b, c = factory(0, "lift-cube"), factory(1, "lift-cube"), factory(2, "lift-cube")
    try:
        assert a.host is b.host and c.host is not a.host  # two robots per actor
        assert _actor_pid(a) != os.getpid() and _actor_pid(a) != _actor_pid(c)  # physics is out of process
        assert a.prioritize(Priority.BACKGROUND) and not a.prioritize(Priority.CONTROL)  # an actor's calls keep order
        _contract(a)  # ends with a's error and kill: b, on the same actor, carries on
        b.request_reset(3)
        c.request_reset(3)
        wait_any([b, c], 120.0, min_ready=2)
        fb, fc = b.poll(), c.poll()
        assert fb is not None and fc is not None and fb.t == 0
        np.testing.assert_allclose(fb.obs, fc.obs)  # same seed, same task: same frame
        again = factory(0, "lift-cube")  # a robot restarted on the actor gets its own answers
        assert again.host is a.host
        again.request_reset(5)
        assert _answer(again).t == 0
    finally:
        for w in (a, b, c):
            w.close()


def test_a_ray_actor_that_dies_faults_its_robots_and_ray_restarts_it(ray_local):
    factory = WORKERS["ray"](Settings(workers={"kind": "ray", "robots_per_process": 4}, ray={"cpus_per_actor": 0.5}))
    a, b = factory(0, "lift-cube"), factory(1, "lift-cube")
    try:
        a.request_reset(1)
        b.request_reset(1)
        wait_any([a, b], 120.0, min_ready=2)
        assert a.poll() is not None and b.poll() is not None
        pid = _actor_pid(a)
        a.request_step(np.zeros(10))  # in flight when the actor's process dies
        os.kill(pid, 9)
        with pytest.raises(WorkerFault, match="died"):
            _answer(a, timeout=60)
        b.request_reset(2)  # idle when it died: its next request finds the restarted actor without its task
        with pytest.raises(WorkerFault, match="not open|died"):
            _answer(b, timeout=60)
        a.kill()
        b.kill()
        fresh = factory(0, "lift-cube")  # the fleet's restart: the same actor, restarted by Ray
        fresh.request_reset(1)
        assert _answer(fresh, timeout=120).t == 0
        assert _actor_pid(fresh) != pid
        fresh.close()
    finally:
        a.kill()
        b.kill()


def test_a_ray_robot_whose_task_cannot_be_built_faults_alone(ray_local):
    factory = WORKERS["ray"](Settings(workers={"kind": "ray", "robots_per_process": 4}, ray={"cpus_per_actor": 0.5}))
    bad, good = factory(0, "no-such-task"), factory(1, "lift-cube")
    try:
        bad.request_reset(1)
        with pytest.raises(WorkerFault, match="no-such-task"):
            _answer(bad, timeout=60)
        good.request_reset(1)
        assert _answer(good).t == 0
        good.request_step(_answer_hold(good))
        assert _answer(good).t == 1
    finally:
        for w in (bad, good):
            w.close()

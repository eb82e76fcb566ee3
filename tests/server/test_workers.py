"""The RobotWorker contract on both back ends: reset, step, non-blocking poll, faults, priority."""

import os
import time

import numpy as np
import pytest

from server.workers import InProcessWorker, Priority, ProcessWorker, WorkerFault, wait_any
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
    worker = ProcessWorker("lift-cube", name="robot-test", niceness=7)
    try:
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

"""What the process-spawning back ends share (``process``: a process per robot; ``pool``: several robots per
process): the spawn context, serving one request of a task, a cheap readiness check on a pipe, and the
mapping of a priority hint to a process's niceness.

Two back ends, one set of parts: ``process`` keeps its own hot path (one request, one answer, no routing)
because the pool with one robot per process steps the fleet more slowly (``hitl bench fleet``,
docs/benchmarks/serving.md): the fleet's default back end is not made slower for fewer lines.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import select
import traceback
from multiprocessing.connection import Connection

import numpy as np

from sim.frame import RobotFrame

log = logging.getLogger("hitl.workers")

SPAWN = mp.get_context("spawn")


def serve_request(task, cmd: str, arg) -> tuple[str, object]:
    """``("ok", frame)`` after a ``reset`` (arg: the seed) or a ``step`` (arg: (action, hold)) of ``task``;
    ``("error", traceback)`` when it raised: the fleet decides what a fault means."""
    try:
        if cmd == "reset":
            task.reset(int(arg))
            return "ok", RobotFrame.from_task(task)
        action, hold = arg
        return "ok", RobotFrame.from_task(task, task.step(np.asarray(action, np.float64), hold))
    except Exception:  # noqa: BLE001 - reported to the robot's worker, the process serves on
        return "error", traceback.format_exc(limit=3)


def readable(conn: Connection) -> select.poll:
    """A poller of ``conn``: ``poll(0)`` says whether something can be read (or its other end is gone) in one
    system call, where ``Connection.poll`` builds a selector each time."""
    poller = select.poll()
    poller.register(conn.fileno(), select.POLLIN)
    return poller


class Niceness:
    """One worker process's CPU priority: the control loop's (0) while it serves a teleoperated robot,
    ``niceness`` (lower) otherwise, so the batched policy step does not queue behind the physics it feeds
    on a machine with fewer cores than robots. Raising a priority again needs CAP_SYS_NICE; without it the
    process stays at ``niceness`` (logged once per service)."""

    denied = False

    def __init__(self, niceness: int) -> None:
        self.niceness = niceness
        self._set: int | None = None  # the niceness set last (None: not since spawn)

    def apply(self, pid: int | None, control: bool) -> bool:
        """Sets the process ``pid``'s niceness for ``control``; False where it could not be raised."""
        want = 0 if control else self.niceness
        if self._set == want or pid is None:
            return True
        try:
            os.setpriority(os.PRIO_PROCESS, pid, want)
        except PermissionError:
            if not Niceness.denied:
                log.info("cannot raise worker priority for teleoperated robots (needs CAP_SYS_NICE)")
            Niceness.denied = True
            if self._set != self.niceness:
                with contextlib.suppress(PermissionError, ProcessLookupError):
                    os.setpriority(os.PRIO_PROCESS, pid, self.niceness)
                    self._set = self.niceness
            return False
        except ProcessLookupError:  # exited: the next poll faults it
            return False
        self._set = want
        return True

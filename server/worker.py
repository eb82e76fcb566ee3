"""One simulated robot per worker process: the physics is the CPU cost of a fleet.

The worker owns a ``Task`` and answers requests on a pipe: ``("reset", seed)``,
``("step", action)``, ``("close", None)``. Every answer is a ``RobotFrame`` dict (plain numpy
arrays and numbers; the pipe is internal to the service). The server never waits on one worker
to serve another: it sends and polls.
"""

from __future__ import annotations

import os
import traceback
from multiprocessing.connection import Connection

import numpy as np
from scipy.spatial.transform import Rotation


def _frame(task, t: int, success: bool, done: bool, obs: np.ndarray | None = None) -> dict:
    pos, rot = task.ee_pose()
    privileged = task.privileged() or {}
    return {
        "obs": (task.observe() if obs is None else obs).astype(np.float32),
        "hold": task.hold_action().astype(np.float64),
        "pos": pos,
        "rot": rot,
        "quat": Rotation.from_matrix(rot).as_quat(),
        "gripper": float(task.gripper_opening()),
        "bodies": {k: (np.asarray(p), np.asarray(q)) for k, (p, q) in task.object_poses().items()},
        "goal": {k: _jsonable(v) for k, v in privileged.items()},
        "t": t,
        "success": bool(success),
        "done": bool(done),
        "info": task.episode_info() if done else {},
    }


def _jsonable(v):
    """What a human operator sees of the scene (true poses, the intended goal), as plain JSON values."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def worker_main(conn: Connection, task_name: str) -> None:
    """Process entry point; exits on ``close`` or when the server end of the pipe goes away.

    The server sets the process's CPU priority (see ``Fleet._prioritize``).
    """
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from sim.registry import make_task

    task = make_task(task_name)
    try:
        while True:
            try:
                cmd, arg = conn.recv()
            except (EOFError, OSError):
                return
            try:
                if cmd == "reset":
                    task.reset(int(arg))
                    conn.send(("ok", _frame(task, 0, False, False)))
                elif cmd == "step":
                    r = task.step(np.asarray(arg, dtype=np.float64))
                    conn.send(("ok", _frame(task, r.t, r.success, r.done, r.obs)))
                elif cmd == "close":
                    return
                else:
                    conn.send(("error", f"unknown command {cmd!r}"))
            except Exception:  # report and keep serving: the server decides what a fault means
                conn.send(("error", traceback.format_exc(limit=3)))
    finally:
        task.close()

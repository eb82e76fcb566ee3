"""Robot workers: how the fleet talks to its robots.

- ``base``: the ``RobotWorker`` contract, ``WorkerFault``, ``Priority``, ``wait_any``.
- ``process``: ``ProcessWorker``, one simulated robot per spawned process (its crash, niceness and kill
  are its own).
- ``pool``: ``PoolWorker``, several robots per spawned process, so one wake-up serves several robots'
  steps (a process per robot spends much of a small machine's CPU switching between them).
- ``spawn``: what those two share (spawn context, serving a request, niceness of a priority hint).
- ``in_process``: ``InProcessWorker``, the robot's task stepped in the caller's thread.
- ``ray_actors``: ``RayWorker``, several robots per Ray actor, on a local instance or a cluster
  (``pip install '.[ray]'``; Ray is imported only when used).
- ``registry``: ``WORKERS``, the back ends the settings' ``worker`` name selects from.
"""

from server.workers.base import Priority, RobotWorker, WorkerFactory, WorkerFault, wait_any
from server.workers.in_process import InProcessWorker, in_process_workers
from server.workers.pool import PoolFactory, PoolWorker, pool_workers
from server.workers.process import ProcessWorker, process_workers
from server.workers.registry import WORKERS

__all__ = [
    "WORKERS",
    "InProcessWorker",
    "PoolFactory",
    "PoolWorker",
    "Priority",
    "ProcessWorker",
    "RobotWorker",
    "WorkerFactory",
    "WorkerFault",
    "in_process_workers",
    "pool_workers",
    "process_workers",
    "wait_any",
]

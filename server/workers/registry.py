"""The worker back ends by name: the settings' ``workers.kind`` selects the factory built from the settings.

Kept apart from the contract (``server.workers.base``), so that a back end imports the contract and
the registry imports the back ends, and nothing imports back up. A new back end is a module
implementing ``RobotWorker`` and one line here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from server.workers.base import WorkerFactory
from server.workers.in_process import in_process_workers
from server.workers.pool import pool_workers
from server.workers.process import process_workers
from server.workers.ray_actors import RayFactory

if TYPE_CHECKING:
    from server.settings import Settings


WORKERS: dict[str, Callable[[Settings], WorkerFactory]] = {
    "process": lambda s: process_workers(s.workers.niceness),
    "pool": lambda s: pool_workers(s.workers.niceness, s.workers.robots_per_process),
    "in-process": lambda s: in_process_workers(),
    "ray": lambda s: RayFactory(s.ray, s.workers.robots_per_process, s.ray.cpus_per_actor),
}

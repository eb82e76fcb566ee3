"""The service's one connection to Ray, for the back ends that run on it (``workers.kind``, ``inference.backend``).

Ray is an optional extra (``pip install '.[ray]'``), imported only here and by the back ends that use
it, so a fleet on the embedded defaults never needs it. ``connect`` starts a local instance with the
machine's CPUs and no dashboard, or joins the cluster at ``ray.address`` (``ray://`` or ``host:port``),
once per process: the robot actors and the service share it. The settings' ``ray.namespace`` keeps
one service's actors apart from another's on a shared cluster. ``connect`` reads only those two
settings (``RayTarget``), so this module never imports ``server.settings``, which imports it.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import threading
from typing import Protocol

log = logging.getLogger("hitl.ray")
_lock = threading.Lock()


class RayTarget(Protocol):
    """What ``connect`` reads of the service's settings (``server.settings.RaySettings`` has both)."""

    @property
    def address(self) -> str | None: ...

    @property
    def namespace(self) -> str: ...


class RayUnavailable(RuntimeError):
    """Ray is not installed, or the cluster cannot be reached; the message says which and what to do."""


def ray_available() -> bool:
    """Whether Ray is installed here (without importing it)."""
    return importlib.util.find_spec("ray") is not None


def ray_module():
    """The ``ray`` package, or RayUnavailable naming the extra that installs it."""
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailable("this setting needs Ray, an optional extra: pip install '.[ray]'") from exc
    return ray


def connect(settings: RayTarget):
    """The ``ray`` module, initialized for this service (a local instance, or the cluster at
    ``settings.address``); already initialized: as it is."""
    ray = ray_module()
    with _lock:
        if ray.is_initialized():
            return ray
        kwargs = {
            "namespace": settings.namespace,
            "include_dashboard": False,
            "logging_level": logging.WARNING,
            "log_to_driver": False,
            # the actors import the project from the installed package, as the service does
            "runtime_env": {"env_vars": {"OMP_NUM_THREADS": "1"}},
        }
        if settings.address:
            kwargs["address"] = settings.address
        else:
            kwargs["num_cpus"] = os.cpu_count() or 1
        try:
            ray.init(**kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = settings.address or "a local instance"
            raise RayUnavailable(f"cannot start or join Ray ({where}): {exc}") from exc
        log.info("ray: %s", "joined " + settings.address if settings.address else "local instance started")
        return ray

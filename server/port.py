"""``FleetPort``: all that the REST API and the operator console use of the fleet runtime.

The API's routers (``server.api``) and the console (``web``) reach the fleet only through these
members, typed here, never through its robots, queue, lock or settings. ``server.fleet.fleet.Fleet``
implements it in the process that runs the control loop. A runtime in another process, or a Ray
actor, implements it behind a client, and the API and the console run unchanged against it:
every call below is already one that never waits for a tick in progress, or one that an admin makes
rarely (pause, resume, reset, policies). ``tests/server/test_port.py`` checks that nothing in
``server.api`` or ``web`` reaches past it.

``server.runtime`` is that runtime elsewhere: ``RemoteFleet`` implements the port in an API process,
from the snapshots the runtime publishes and calls on its connections (``server.runtime.host``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from server import registry
from server.cameras import CameraView
from server.fleet.assistance import AssistanceRequest
from server.fleet.metrics import MetricsReport
from server.fleet.robot import RobotView
from sim.spaces import TeleopCommand


class FleetPort(Protocol):
    @property
    def ticks(self) -> int:
        """Control ticks that stepped a robot since the start (0: not serving yet)."""
        ...

    @property
    def remote(self) -> bool:
        """True when each call crosses to a runtime in another process (``server.runtime.client``): the
        async routes then make their calls from the threadpool (``server.api.deps.call_port``)."""
        ...

    @property
    def data_dir(self) -> Path:
        """The service's data root: stored paths (episodes, segments) are relative to it."""
        ...

    # -- what readers see (published snapshots: never waits for a tick) --------------------------------
    def view(self, robot_id: int) -> RobotView:
        """The robot as published; ``ServiceError`` 404 for an unknown robot."""
        ...

    def views(self) -> list[RobotView]: ...

    def requests(self) -> list[AssistanceRequest]:
        """Open assistance requests, unclaimed first, by priority."""
        ...

    def metrics(self) -> MetricsReport: ...

    def camera_view(self, robot_id: int) -> CameraView:
        """The robot's latest camera views, or why there are none (``server.cameras``); asking marks the
        robot watched, and only watched robots are rendered. ``ServiceError`` 404 for an unknown robot."""
        ...

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]: ...

    # -- an operator's takeover (never waits for a tick: ``server.fleet.inbox``) ----------------------------------
    def claim(self, robot_id: int, operator: str) -> AssistanceRequest: ...

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest: ...

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int: ...

    def release(self, robot_id: int, operator: str) -> None: ...

    # -- an admin's (rare) -----------------------------------------------------------------------------------
    def pause(self, robot_id: int) -> None: ...

    def resume(self, robot_id: int) -> None: ...

    def reset(self, robot_id: int) -> None: ...

    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int: ...

    def activate_policy(self, version: int, reason: str | None = None) -> None: ...


MEMBERS = frozenset(n for n in vars(FleetPort) if not n.startswith("_"))

# the role each member that changes something needs, for the REST routes (``server.api``: each route's role
# dependency, checked against this by tests/server/test_port.py) and the console (``web.actions``) alike
NEEDS = {
    "claim": "operator",
    "heartbeat": "operator",
    "command": "operator",
    "release": "operator",
    "pause": "admin",
    "resume": "admin",
    "reset": "admin",
    "register_policy": "admin",
    "activate_policy": "admin",
}

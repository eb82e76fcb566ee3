"""What a console user may do, through the fleet's own service methods with the API's checks.

Every console input comes here: the same role rule as the REST dependencies (claiming, commanding and
handing back need the operator role), the same command checks as ``POST /robots/{id}/command``
(``TeleopCommand.checked``: finite values, per-component bounds, gripper range; the API's body model states
the same bounds), then the same ``Fleet`` method the route calls (lease check, composition limits, 429).
Refusals are ``ServiceError`` with the status the API would answer; the console shows their message.
"""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy.orm import sessionmaker

from server.errors import ServiceError
from server.labels import LabelChange, set_label
from server.port import FleetPort
from sim.spaces import TeleopCommand
from web.identity import Identity


class ConsoleActions:
    """sessions: the service's database, for labelling takeovers (None: labels are refused)."""

    def __init__(self, fleet: FleetPort, identity: Identity, sessions: sessionmaker | None = None) -> None:
        self.fleet, self.identity, self.sessions = fleet, identity, sessions

    @property
    def can_operate(self) -> bool:
        return self.identity.has("operator")

    def _need_operator(self, what: str) -> None:
        if not self.can_operate:
            raise ServiceError(403, f"{what} needs the operator role; you are logged in as {self.identity.role}")

    def claim(self, robot_id: int):
        self._need_operator("claiming a robot")
        return self.fleet.claim(robot_id, self.identity.name)

    def heartbeat(self, robot_id: int):
        self._need_operator("holding a robot")
        return self.fleet.heartbeat(robot_id, self.identity.name)

    def release(self, robot_id: int) -> None:
        self._need_operator("handing a robot back")
        self.fleet.release(robot_id, self.identity.name)

    def command(self, robot_id: int, delta_pos: Sequence[float], delta_rot: Sequence[float], gripper: float) -> int:
        """One teleop command; returns how many commands the next tick applies."""
        self._need_operator("commanding a robot")
        try:
            command = TeleopCommand.checked(delta_pos, delta_rot, gripper)
        except ValueError as exc:
            raise ServiceError(422, str(exc)) from exc
        return self.fleet.command(robot_id, self.identity.name, command)

    def label(self, segment_id: int, change: LabelChange) -> None:
        """Labels a takeover (as ``PATCH /segments/{id}``: the operator role, the same checks)."""
        self._need_operator("labelling a takeover")
        if self.sessions is None:
            raise ServiceError(503, "this console has no database to keep labels in")
        set_label(self.sessions, segment_id, self.identity.name, change)

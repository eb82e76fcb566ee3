"""What a console user may do: the fleet's own port members, behind the API's rules.

Every console input comes here and meets the same rules as the REST route that does the same: the role
the port names for the member (``server.port.NEEDS``: claiming, commanding and handing back need the
operator role), the API's body model for a command (``server.api.schemas.TeleopCommandIn``: finite values,
per-component bounds, gripper range), then the same port member the route calls (lease check, composition
limits, 429). Refusals are ``ServiceError`` with the status the API would answer; the console shows their
message.
"""

from __future__ import annotations

from collections.abc import Sequence

from pydantic import ValidationError
from sqlalchemy.orm import sessionmaker

from server.api.schemas import TeleopCommandIn
from server.auth import forbidden
from server.errors import ServiceError
from server.labels import LabelChange, set_label
from server.port import NEEDS, FleetPort
from web.identity import Identity


class ConsoleActions:
    """sessions: the service's database, for labelling takeovers (None: labels are refused)."""

    def __init__(self, fleet: FleetPort, identity: Identity, sessions: sessionmaker | None = None) -> None:
        self.fleet, self.identity, self.sessions = fleet, identity, sessions

    @property
    def can_operate(self) -> bool:
        return self.identity.has(NEEDS["claim"])

    def _allowed(self, member: str) -> None:
        if not self.identity.has(NEEDS[member]):
            raise ServiceError(403, forbidden(NEEDS[member], self.identity.role))

    def claim(self, robot_id: int):
        self._allowed("claim")
        return self.fleet.claim(robot_id, self.identity.name)

    def heartbeat(self, robot_id: int):
        self._allowed("heartbeat")
        return self.fleet.heartbeat(robot_id, self.identity.name)

    def release(self, robot_id: int) -> None:
        self._allowed("release")
        self.fleet.release(robot_id, self.identity.name)

    def command(self, robot_id: int, delta_pos: Sequence[float], delta_rot: Sequence[float], gripper: float) -> int:
        """One teleop command; returns how many commands the next tick applies."""
        self._allowed("command")
        try:
            body = TeleopCommandIn(delta_pos=list(delta_pos), delta_rot=list(delta_rot), gripper=gripper)
        except ValidationError as exc:
            raise ServiceError(422, "; ".join(e["msg"] for e in exc.errors())) from exc
        return self.fleet.command(robot_id, self.identity.name, body.to_command())

    def label(self, segment_id: int, change: LabelChange) -> None:
        """Labels a takeover (as ``PATCH /segments/{id}``: the operator role, the same checks)."""
        if not self.identity.has("operator"):
            raise ServiceError(403, forbidden("operator", self.identity.role))
        if self.sessions is None:
            raise ServiceError(503, "this console has no database to keep labels in")
        set_label(self.sessions, segment_id, self.identity.name, change)

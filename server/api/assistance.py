"""``/assistance``: the queue of open assistance requests. Claiming a robot, renewing and handing back
its lease and the teleop commands (REST and WebSocket) are routes of the robots resource
(``server.api.robots``), tagged ``assistance``."""

from __future__ import annotations

import time

from fastapi import APIRouter

from server.api.deps import FleetDep, Viewer
from server.api.responses import AUTH, errors
from server.api.schemas import AssistanceRequestOut
from server.fleet.assistance import AssistanceRequest

router = APIRouter(tags=["assistance"])


def request_out(req: AssistanceRequest) -> AssistanceRequestOut:
    """The answer for one request (the queue, and a claim or heartbeat in ``server.api.robots``)."""
    now = time.monotonic()
    return AssistanceRequestOut(
        id=req.id,
        robot_id=req.robot_id,
        signal=req.signal,
        score=req.score,
        uncertainty=req.score,
        threshold=req.threshold,
        reason=req.reason,
        waiting_s=now - req.created,
        priority=req.priority(now),
        holder=req.holder,
        lease_expires_in_s=None if req.lease_until is None else req.lease_until - now,
    )


@router.get("/assistance", response_model=list[AssistanceRequestOut], responses=errors(AUTH))
async def queue(fleet: FleetDep, _: Viewer) -> list[AssistanceRequestOut]:
    """Open requests, unclaimed first, by priority: how far the score is over its threshold (as a fraction
    of the score, 0 to 1) plus one unit per 10 s waited, so no robot waits long whatever its signal's scale
    (``server.fleet.assistance``)."""
    return [request_out(r) for r in fleet.requests()]

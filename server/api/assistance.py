"""``/assistance``: the queue; claim, heartbeat and release a robot; teleop commands (REST and
WebSocket)."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from server.api.deps import FleetDep, Operator, Viewer, call_port, websocket_principal
from server.api.responses import AUTH, BODY, errors
from server.api.robots import detail, summary
from server.api.schemas import AssistanceRequestOut, CommandAccepted, Id, RobotSummary, TeleopCommandIn
from server.api.ws_messages import (
    CLOSE_UNKNOWN_ROBOT,
    STATE_PERIOD_S,
    TeleopAcceptedMessage,
    TeleopErrorMessage,
    TeleopStateMessage,
    read_command,
)
from server.assistance import AssistanceRequest
from server.errors import ServiceError
from server.port import FleetPort

router = APIRouter(tags=["assistance"])


def _out(req: AssistanceRequest) -> AssistanceRequestOut:
    now = time.monotonic()
    return AssistanceRequestOut(
        id=req.id,
        robot_id=req.robot_id,
        uncertainty=req.uncertainty,
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
    (``server.assistance``)."""
    return [_out(r) for r in fleet.requests()]


_HOLDER = errors(
    AUTH,
    404,
    409,
    422,
    why={404: "no such robot", 409: "no open assistance request, or another operator holds the robot"},
)


@router.post("/robots/{robot_id}/claim", response_model=AssistanceRequestOut, responses=_HOLDER)
async def claim(robot_id: Id, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    """Take control of a robot that asked for help: a lease, renewed by heartbeats. The robot is under
    your control from the fleet's next tick; commands sent before it are applied at that tick."""
    return _out(await call_port(fleet, fleet.claim, robot_id, who.name))


@router.post("/robots/{robot_id}/heartbeat", response_model=AssistanceRequestOut, responses=_HOLDER)
async def heartbeat(robot_id: Id, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    return _out(await call_port(fleet, fleet.heartbeat, robot_id, who.name))


@router.post("/robots/{robot_id}/release", response_model=RobotSummary, responses=_HOLDER)
async def release(robot_id: Id, fleet: FleetDep, who: Operator) -> RobotSummary:
    """Hand the robot back to its policy (at the fleet's next tick; it is shown handed back at once)."""
    await call_port(fleet, fleet.release, robot_id, who.name)
    return summary(fleet.view(robot_id))


@router.post(
    "/robots/{robot_id}/command",
    response_model=CommandAccepted,
    responses=errors(
        AUTH,
        BODY,
        404,
        409,
        429,
        why={404: "no such robot", 409: "the robot is not under teleop, or you do not hold it"},
    ),
)
async def command(robot_id: Id, body: TeleopCommandIn, fleet: FleetDep, who: Operator) -> CommandAccepted:
    """One teleop command, applied exactly once at the next control tick. Only the lease holder may
    command. Commands arriving between two ticks compose into that tick's step (translations add,
    rotations compose in order, the newest gripper command wins); a command that would take the
    composed step over the per-step limits (3 cm, 0.2 rad) is refused with 429 and nothing waiting
    changes: send it again after the next tick. ``pending`` says how many commands the next tick
    applies. 409 for a robot that is not under teleop (autonomous, waiting, paused, ...) or that another
    operator holds; 404 only for an unknown robot."""
    pending = await call_port(fleet, fleet.command, robot_id, who.name, body.to_command())
    return CommandAccepted(robot_id=robot_id, pending=pending)


@router.websocket("/robots/{robot_id}/teleop")
async def teleop_socket(websocket: WebSocket, robot_id: int) -> None:
    """Commands in (``TeleopCommandIn``), robot state out (``TeleopStateMessage``, every 0.1 s), and one
    ``TeleopAcceptedMessage`` or ``TeleopErrorMessage`` answering each message, in order. The message models
    and their schemas: ``server.api.ws_messages``; the protocol: docs/websocket.md.

    Auth: ``Authorization: Bearer`` header or ``?token=`` (HTTP 401 without a valid token); commands
    need the operator role (a 403 reply otherwise). A refused message changes nothing and the socket
    stays open; an unknown robot gets a 404 error message and the close code 4404.
    """
    fleet: FleetPort = websocket.app.state.fleet
    principal = await websocket_principal(websocket, "viewer")
    if principal is None:
        await websocket.send_denial_response(JSONResponse({"detail": "missing or invalid API token"}, status_code=401))
        return
    await websocket.accept()
    try:
        fleet.view(robot_id)
    except ServiceError as exc:
        await _send(websocket, TeleopErrorMessage(error=str(exc), status=exc.status))
        await websocket.close(code=CLOSE_UNKNOWN_ROBOT)
        return
    max_bytes = websocket.app.state.settings.max_body_bytes

    async def send_state() -> None:
        while True:
            await _send(websocket, TeleopStateMessage(state=detail(fleet.view(robot_id))))
            await asyncio.sleep(STATE_PERIOD_S)

    sender = asyncio.create_task(send_state())
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            if not principal.has("operator"):
                await _send(websocket, TeleopErrorMessage(error="commanding needs the operator role", status=403))
                continue
            body = read_command(message, max_bytes)  # bad values are not echoed
            if isinstance(body, TeleopErrorMessage):
                await _send(websocket, body)
                continue
            try:
                pending = await call_port(fleet, fleet.command, robot_id, principal.name, body.to_command())
            except ServiceError as exc:
                await _send(websocket, TeleopErrorMessage(error=str(exc), status=exc.status))
                continue
            await _send(websocket, TeleopAcceptedMessage(pending=pending))
    except WebSocketDisconnect:
        pass
    finally:
        sender.cancel()
        await asyncio.gather(sender, return_exceptions=True)  # a send that failed on a closed socket ends here


async def _send(websocket: WebSocket, message: BaseModel) -> None:
    await websocket.send_json(message.model_dump(mode="json"))

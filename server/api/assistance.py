"""``/assistance``: the queue; claim, heartbeat and release a robot; teleop commands (REST and
WebSocket)."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from server.api.deps import FleetDep, Operator, Viewer, websocket_principal
from server.api.robots import detail, summary
from server.api.schemas import AssistanceRequestOut, CommandAccepted, RobotSummary, TeleopCommandIn
from server.assistance import AssistanceRequest
from server.errors import ServiceError
from server.fleet import Fleet
from sim.spaces import TeleopCommand

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


@router.get("/assistance", response_model=list[AssistanceRequestOut])
def queue(fleet: FleetDep, _: Viewer) -> list[AssistanceRequestOut]:
    """Open requests, unclaimed first, by priority (uncertainty relative to threshold, and waiting time)."""
    return [_out(r) for r in fleet.queue.pending()]


@router.post("/robots/{robot_id}/claim", response_model=AssistanceRequestOut)
def claim(robot_id: int, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    """Take control of a robot that asked for help: a lease, renewed by heartbeats."""
    return _out(fleet.claim(robot_id, who.name))


@router.post("/robots/{robot_id}/heartbeat", response_model=AssistanceRequestOut)
def heartbeat(robot_id: int, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    return _out(fleet.heartbeat(robot_id, who.name))


@router.post("/robots/{robot_id}/release", response_model=RobotSummary)
def release(robot_id: int, fleet: FleetDep, who: Operator) -> RobotSummary:
    """Hand the robot back to its policy."""
    fleet.release(robot_id, who.name)
    return summary(fleet.view(robot_id))


def _command(body: TeleopCommandIn) -> TeleopCommand:
    return TeleopCommand(tuple(body.delta_pos), tuple(body.delta_rot), body.gripper)


@router.post("/robots/{robot_id}/command", response_model=CommandAccepted)
def command(robot_id: int, body: TeleopCommandIn, fleet: FleetDep, who: Operator) -> CommandAccepted:
    """One teleop command, applied exactly once at the next control tick. Only the lease holder may
    command. Commands arriving between two ticks compose into that tick's step (translations add,
    rotations compose in order, the newest gripper command wins); a command that would take the
    composed step over the per-step limits (3 cm, 0.2 rad) is refused with 429 and nothing waiting
    changes: send it again after the next tick. ``pending`` says how many commands the next tick
    applies."""
    pending = fleet.command(robot_id, who.name, _command(body))
    return CommandAccepted(robot_id=robot_id, pending=pending)


@router.websocket("/robots/{robot_id}/teleop")
async def teleop_socket(websocket: WebSocket, robot_id: int) -> None:
    """Streams commands in (TeleopCommandIn JSON) and robot state out (RobotDetail JSON, ~10 Hz).

    Auth: ``Authorization: Bearer`` header or ``?token=`` (HTTP 401 without a valid token); commands
    need the operator role (a 403 reply otherwise).
    """
    fleet: Fleet = websocket.app.state.fleet
    principal = websocket_principal(websocket, "viewer")
    if principal is None:
        await websocket.send_denial_response(JSONResponse({"detail": "missing or invalid API token"}, status_code=401))
        return
    await websocket.accept()
    try:
        fleet.robot(robot_id)
    except ServiceError as exc:
        await websocket.send_json({"error": str(exc), "status": exc.status})
        await websocket.close(code=4404)
        return

    async def send_state() -> None:
        while True:
            state = detail(fleet.view(robot_id)).model_dump(mode="json")
            await websocket.send_json({"state": state})
            await asyncio.sleep(0.1)

    sender = asyncio.create_task(send_state())
    try:
        while True:
            data = await websocket.receive_json()
            if not principal.has("operator"):
                await websocket.send_json({"error": "commanding needs the operator role", "status": 403})
                continue
            try:
                cmd = _command(TeleopCommandIn.model_validate(data))
                pending = fleet.command(robot_id, principal.name, cmd)
                await websocket.send_json({"accepted": True, "pending": pending})
            except ValidationError as exc:
                errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
                await websocket.send_json({"error": errors, "status": 422})  # bad values are not echoed
            except ServiceError as exc:
                await websocket.send_json({"error": str(exc), "status": exc.status})
    except WebSocketDisconnect:
        pass
    finally:
        sender.cancel()

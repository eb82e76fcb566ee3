"""``/robots``: list, get, operator view; pause, resume, reset (admin); claim, heartbeat, release and
teleop commands (REST and WebSocket) of an operator.

The reads are ``async``: they only read each robot's published snapshot, never the fleet lock, so
they run on the event loop without a threadpool hop. The control routes take the fleet lock (they
wait for a tick in progress) and stay synchronous, in the threadpool. The operator's routes go through
``call_port`` (``server.api.deps``).

The operator's routes keep the ``assistance`` tag they are documented under (the queue's); the others
are tagged ``robots``."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from server.api.assistance import request_out
from server.api.deps import Admin, FleetDep, Operator, Viewer, call_port, websocket_principal
from server.api.responses import AUTH, BODY, errors
from server.api.schemas import (
    AskingOut,
    AssistanceRequestOut,
    CommandAccepted,
    Id,
    OperatorView,
    PaperMetricOut,
    PoseOut,
    RobotDetail,
    RobotSummary,
    TeleopCommandIn,
    UncertaintyOut,
)
from server.api.ws_messages import (
    CLOSE_UNKNOWN_ROBOT,
    STATE_PERIOD_S,
    TeleopAcceptedMessage,
    TeleopErrorMessage,
    TeleopStateMessage,
    read_command,
)
from server.errors import ServiceError
from server.fleet.robot import RobotView
from server.port import FleetPort

router = APIRouter(prefix="/robots")  # each route names its tag: a router's tags would add to them
ROBOTS, ASSISTANCE = ["robots"], ["assistance"]


def _pose(p, q) -> PoseOut:
    return PoseOut(position=[float(x) for x in p], quaternion=[float(x) for x in q])


def _uncertainty(robot: RobotView) -> UncertaintyOut | None:
    r = robot.last_result
    if r is None:
        return None
    return UncertaintyOut(
        U=r.U,
        D=r.D,
        var_g=r.var_g,
        n=r.n,
        threshold=robot.slot.threshold,
        samples=r.samples.tolist(),
        vectors=r.vectors.tolist(),
        labels=r.labels.tolist(),
        means=r.means.tolist(),
        weights=r.weights.tolist(),
    )


def asking(robot: RobotView) -> AskingOut:
    """The asking signal's numbers: the open request's (``RobotView.ask``, the queue's own record) while
    the robot has one, else the signal's latest score and decision."""
    name = robot.slot.asking or None
    ask = robot.ask
    if ask is None:
        return AskingOut(
            signal=name,
            score=robot.scores.get(name) if name else None,
            threshold=robot.slot.asking_threshold,
            wants_help=robot.wants.get(name) if name else None,
            reason=None,
            asked_at_step=None,
        )
    return AskingOut(
        signal=ask.signal,
        score=ask.score,
        threshold=ask.threshold,
        wants_help=robot.wants.get(name) if name and ask.signal == name else None,
        reason=ask.reason,
        asked_at_step=ask.asked_at_step,
    )


def summary(robot: RobotView) -> RobotSummary:
    """``uncertainty`` and ``threshold`` are the asking signal's (``asking``); the paper's metric is ``paper``."""
    now = asking(robot)
    return RobotSummary(
        id=robot.id,
        task=robot.task,
        mode=robot.mode,
        policy_version=robot.slot.version,
        episode_id=robot.episode_id,
        episode_step=robot.steps,
        uncertainty=now.score,
        threshold=now.threshold,
        asking=now,
        paper=PaperMetricOut(U=robot.u_history[-1] if robot.u_history else None, threshold=robot.slot.threshold),
    )


def _bodies(robot: RobotView) -> dict[str, PoseOut]:
    frame = robot.frame
    return {k: _pose(p, q) for k, (p, q) in frame.bodies.items()} if frame else {}


def detail(robot: RobotView) -> RobotDetail:
    frame = robot.frame
    return RobotDetail(
        **summary(robot).model_dump(),
        pose=_pose(frame.pos, frame.quat) if frame else None,
        gripper=frame.gripper if frame else None,
        bodies=_bodies(robot),
        u_history=list(robot.u_history),
        score_history=list(robot.score_history),
        last_uncertainty=_uncertainty(robot),
        episodes_done=robot.episodes_done,
        successes=robot.successes,
        assisted_steps=robot.assisted_steps,
        assistance_events=robot.events,
        restarts=robot.restarts,
        fault=robot.fault,
    )


def _get(fleet: FleetPort, robot_id: int) -> RobotView:
    return fleet.view(robot_id)


@router.get("", response_model=list[RobotSummary], responses=errors(AUTH), tags=ROBOTS)
async def list_robots(fleet: FleetDep, _: Viewer) -> list[RobotSummary]:
    return [summary(r) for r in fleet.views()]


@router.get("/{robot_id}", response_model=RobotDetail, responses=errors(AUTH, 404, 422), tags=ROBOTS)
async def get_robot(robot_id: Id, fleet: FleetDep, _: Viewer) -> RobotDetail:
    return detail(_get(fleet, robot_id))


@router.get("/{robot_id}/view", response_model=OperatorView, responses=errors(AUTH, 404, 422), tags=ROBOTS)
async def operator_view(robot_id: Id, fleet: FleetDep, _: Viewer) -> OperatorView:
    """What a human operator sees: the scene's body poses, the goal, the last denoising result and why the
    robot asked (``asking``)."""
    robot = _get(fleet, robot_id)
    frame = robot.frame
    return OperatorView(
        robot_id=robot.id,
        task=robot.task,
        mode=robot.mode,
        pose=_pose(frame.pos, frame.quat) if frame else None,
        gripper=frame.gripper if frame else None,
        bodies=_bodies(robot),
        goal=frame.goal if frame else {},
        last_uncertainty=_uncertainty(robot),
        asking=asking(robot),
        episode_seed=robot.seed,
        step=frame.t if frame else None,
        clock=frame.clock if frame else None,
        horizon=frame.horizon if frame else None,
        events=robot.events,
    )


_CONTROL = errors(AUTH, 404, 409, 422, why={409: "the robot is faulted (pause, reset) or not paused (resume)"})


@router.post("/{robot_id}/pause", response_model=RobotSummary, responses=_CONTROL, tags=ROBOTS)
def pause(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.pause(robot_id)
    return summary(fleet.view(robot_id))


@router.post("/{robot_id}/resume", response_model=RobotSummary, responses=_CONTROL, tags=ROBOTS)
def resume(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.resume(robot_id)
    return summary(fleet.view(robot_id))


@router.post("/{robot_id}/reset", response_model=RobotSummary, responses=_CONTROL, tags=ROBOTS)
def reset(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.reset(robot_id)
    return summary(fleet.view(robot_id))


# -- an operator: claim, heartbeat, release, commands ---------------------------------------------------
_HOLDER = errors(
    AUTH,
    404,
    409,
    422,
    why={404: "no such robot", 409: "no open assistance request, or another operator holds the robot"},
)


@router.post("/{robot_id}/claim", response_model=AssistanceRequestOut, responses=_HOLDER, tags=ASSISTANCE)
async def claim(robot_id: Id, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    """Take control of a robot that asked for help: a lease, renewed by heartbeats. The robot is under
    your control from the fleet's next tick; commands sent before it are applied at that tick."""
    return request_out(await call_port(fleet, fleet.claim, robot_id, who.name))


@router.post("/{robot_id}/heartbeat", response_model=AssistanceRequestOut, responses=_HOLDER, tags=ASSISTANCE)
async def heartbeat(robot_id: Id, fleet: FleetDep, who: Operator) -> AssistanceRequestOut:
    return request_out(await call_port(fleet, fleet.heartbeat, robot_id, who.name))


@router.post("/{robot_id}/release", response_model=RobotSummary, responses=_HOLDER, tags=ASSISTANCE)
async def release(robot_id: Id, fleet: FleetDep, who: Operator) -> RobotSummary:
    """Hand the robot back to its policy at the fleet's next tick; your commands are refused from now on."""
    await call_port(fleet, fleet.release, robot_id, who.name)
    return summary(fleet.view(robot_id))


@router.post(
    "/{robot_id}/command",
    response_model=CommandAccepted,
    responses=errors(
        AUTH,
        BODY,
        404,
        409,
        429,
        why={404: "no such robot", 409: "the robot is not under teleop, or you do not hold it"},
    ),
    tags=ASSISTANCE,
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


@router.websocket("/{robot_id}/teleop")
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

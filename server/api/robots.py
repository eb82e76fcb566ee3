"""``/robots``: list, get, operator view; pause, resume, reset (admin).

The reads are ``async``: they only read each robot's published snapshot, never the fleet lock, so
they run on the event loop without a threadpool hop. The control routes take the fleet lock (they
wait for a tick in progress) and stay synchronous, in the threadpool."""

from __future__ import annotations

from fastapi import APIRouter

from server.api.deps import Admin, FleetDep, Viewer
from server.api.responses import AUTH, errors
from server.api.schemas import Id, OperatorView, PoseOut, RobotDetail, RobotSummary, UncertaintyOut
from server.port import FleetPort
from server.robot import RobotView

router = APIRouter(prefix="/robots", tags=["robots"])


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


def summary(robot: RobotView) -> RobotSummary:
    return RobotSummary(
        id=robot.id,
        task=robot.task,
        mode=robot.mode,
        policy_version=robot.slot.version,
        episode_id=robot.episode_id,
        episode_step=robot.steps,
        uncertainty=robot.u_history[-1] if robot.u_history else None,
        threshold=robot.slot.threshold,
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


@router.get("", response_model=list[RobotSummary], responses=errors(AUTH))
async def list_robots(fleet: FleetDep, _: Viewer) -> list[RobotSummary]:
    return [summary(r) for r in fleet.views()]


@router.get("/{robot_id}", response_model=RobotDetail, responses=errors(AUTH, 404, 422))
async def get_robot(robot_id: Id, fleet: FleetDep, _: Viewer) -> RobotDetail:
    return detail(_get(fleet, robot_id))


@router.get("/{robot_id}/view", response_model=OperatorView, responses=errors(AUTH, 404, 422))
async def operator_view(robot_id: Id, fleet: FleetDep, _: Viewer) -> OperatorView:
    """What a human operator sees: the scene's body poses, the goal and the last denoising result."""
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
        episode_seed=robot.seed,
        step=frame.t if frame else None,
        clock=frame.clock if frame else None,
        horizon=frame.horizon if frame else None,
        events=robot.events,
    )


_CONTROL = errors(AUTH, 404, 409, 422, why={409: "the robot is faulted (pause, reset) or not paused (resume)"})


@router.post("/{robot_id}/pause", response_model=RobotSummary, responses=_CONTROL)
def pause(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.pause(robot_id)
    return summary(fleet.view(robot_id))


@router.post("/{robot_id}/resume", response_model=RobotSummary, responses=_CONTROL)
def resume(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.resume(robot_id)
    return summary(fleet.view(robot_id))


@router.post("/{robot_id}/reset", response_model=RobotSummary, responses=_CONTROL)
def reset(robot_id: Id, fleet: FleetDep, _: Admin) -> RobotSummary:
    fleet.reset(robot_id)
    return summary(fleet.view(robot_id))

"""``/episodes``, ``/segments`` (list, filter, download the MCAP file), ``/policies``."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from server.api.deps import Admin, FleetDep, SessionsDep, Viewer
from server.api.responses import AUTH, BODY, errors
from server.api.schemas import EpisodeOut, Id, PolicyIn, PolicyOut, SegmentOut
from server.db import EpisodeRecord, PolicyVersion, SegmentRecord
from server.errors import ServiceError
from server.recording import resolve

router = APIRouter(tags=["records"])


@router.get("/episodes", response_model=list[EpisodeOut], responses=errors(AUTH, 422))
def episodes(
    sessions: SessionsDep,
    _: Viewer,
    robot_id: Id | None = None,
    task: str | None = None,
    outcome: str | None = None,
    limit: int = Query(100, ge=1, le=1000),
) -> list[EpisodeRecord]:
    q = select(EpisodeRecord).order_by(EpisodeRecord.id.desc()).limit(limit)
    if robot_id is not None:
        q = q.where(EpisodeRecord.robot_id == robot_id)
    if task is not None:
        q = q.where(EpisodeRecord.task == task)
    if outcome is not None:
        q = q.where(EpisodeRecord.outcome == outcome)
    with sessions() as s:
        return list(s.scalars(q))


@router.get("/segments", response_model=list[SegmentOut], responses=errors(AUTH, 422))
def segments(
    sessions: SessionsDep,
    _: Viewer,
    robot_id: Id | None = None,
    task: str | None = None,
    status: str | None = None,
    operator: str | None = None,
    limit: int = Query(100, ge=1, le=1000),
) -> list[SegmentRecord]:
    q = select(SegmentRecord).order_by(SegmentRecord.id.desc()).limit(limit)
    for column, value in (
        (SegmentRecord.robot_id, robot_id),
        (SegmentRecord.task, task),
        (SegmentRecord.status, status),
        (SegmentRecord.operator, operator),
    ):
        if value is not None:
            q = q.where(column == value)
    with sessions() as s:
        return list(s.scalars(q))


@router.get(
    "/segments/{segment_id}/mcap",
    response_class=FileResponse,
    responses={
        200: {
            "description": "the segment's MCAP file",
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        }
    }
    | errors(AUTH, 404, 409, 410, 422, why={404: "no such segment", 409: "the segment is still being recorded"}),
)
def download_segment(segment_id: Id, sessions: SessionsDep, fleet: FleetDep, _: Viewer) -> FileResponse:
    with sessions() as s:
        row = s.get(SegmentRecord, segment_id)
    if row is None:
        raise HTTPException(404, f"no segment {segment_id}")
    if row.status == "open":
        raise HTTPException(409, f"segment {segment_id} is still being recorded")
    path = resolve(fleet.settings.data_dir, row.path)
    if not path.is_file():
        raise HTTPException(410, f"segment {segment_id}'s file is gone")
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


def _policy_out(sessions, fleet, version: int | None = None) -> list[PolicyOut]:
    q = select(PolicyVersion).order_by(PolicyVersion.id)
    if version is not None:
        q = q.where(PolicyVersion.id == version)
    with sessions() as s:
        rows = list(s.scalars(q))
    running: dict[int, list[int]] = {}
    for r in fleet.views():
        running.setdefault(r.slot.version, []).append(r.id)
    return [PolicyOut.model_validate(row).model_copy(update={"robots": running.get(row.id, [])}) for row in rows]


@router.get("/policies", response_model=list[PolicyOut], responses=errors(AUTH))
def policies(sessions: SessionsDep, fleet: FleetDep, _: Viewer) -> list[PolicyOut]:
    """Policy versions with their status (candidate, active, retired), parent and running robots."""
    return _policy_out(sessions, fleet)


@router.post(
    "/policies",
    response_model=PolicyOut,
    status_code=201,
    responses=errors(
        AUTH,
        BODY,
        404,
        why={404: "no policy version parent_id", 422: "the request does not validate, or the folder is no policy"},
    ),
)
def register_policy(body: PolicyIn, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Registers a policy folder as a ``candidate`` version (the same folder again: the same version)."""
    try:
        version = fleet.register_policy(Path(body.path), body.task, body.parent_id)
    except OSError as exc:  # the folder cannot be looked at: a name too long, no permission, ...
        raise ServiceError(422, f"policy folder {body.path!r} cannot be read: {exc.strerror}") from exc
    return _policy_out(sessions, fleet, version)[0]


@router.post(
    "/policies/{version}/activate",
    response_model=PolicyOut,
    responses=errors(
        AUTH,
        404,
        409,
        422,
        why={
            404: "no such policy version",
            409: "no robot of the fleet runs the version's task",
            422: "the request does not validate, or the version's folder cannot be loaded",
        },
    ),
)
def activate_policy(version: Id, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Serves this version to the robots of its task, without a restart: the checkpoint, trace and
    signals load first, then each robot moves at its next episode boundary (an episode in progress
    finishes on the version it started with). The task's previously active version is retired."""
    fleet.activate_policy(version)
    return _policy_out(sessions, fleet, version)[0]

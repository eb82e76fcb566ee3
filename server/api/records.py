"""``/episodes``, ``/segments`` (list, filter, download the MCAP file), ``/policies``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from sqlalchemy import select

from server.api.deps import Admin, FleetDep, SessionsDep, Viewer
from server.api.schemas import EpisodeOut, PolicyIn, PolicyOut, SegmentOut
from server.db import EpisodeRecord, PolicyVersion, SegmentRecord

router = APIRouter(tags=["records"])


@router.get("/episodes", response_model=list[EpisodeOut])
def episodes(
    sessions: SessionsDep,
    _: Viewer,
    robot_id: int | None = None,
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


@router.get("/segments", response_model=list[SegmentOut])
def segments(
    sessions: SessionsDep,
    _: Viewer,
    robot_id: int | None = None,
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


@router.get("/segments/{segment_id}/mcap", response_class=FileResponse)
def download_segment(segment_id: int, sessions: SessionsDep, _: Viewer) -> FileResponse:
    with sessions() as s:
        row = s.get(SegmentRecord, segment_id)
    if row is None:
        raise HTTPException(404, f"no segment {segment_id}")
    if row.status == "open":
        raise HTTPException(409, f"segment {segment_id} is still being recorded")
    path = Path(row.path)
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


@router.get("/policies", response_model=list[PolicyOut])
def policies(sessions: SessionsDep, fleet: FleetDep, _: Viewer) -> list[PolicyOut]:
    """Policy versions with their status (candidate, active, retired), parent and running robots."""
    return _policy_out(sessions, fleet)


@router.post("/policies", response_model=PolicyOut, status_code=201)
def register_policy(body: PolicyIn, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Registers a policy folder as a ``candidate`` version (the same folder again: the same version)."""
    version = fleet.register_policy(Path(body.path), body.task, body.parent_id)
    return _policy_out(sessions, fleet, version)[0]


@router.post("/policies/{version}/activate", response_model=PolicyOut)
def activate_policy(
    version: Annotated[int, PathParam(ge=1, le=2**62)], sessions: SessionsDep, fleet: FleetDep, _: Admin
) -> PolicyOut:
    """Serves this version to the robots of its task, without a restart: the checkpoint, trace and
    signals load first, then each robot moves at its next episode boundary (an episode in progress
    finishes on the version it started with). The task's previously active version is retired."""
    fleet.activate_policy(version)
    return _policy_out(sessions, fleet, version)[0]

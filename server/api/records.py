"""``/episodes``, ``/segments`` (list, filter, download the MCAP file, label a takeover)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from server.api.deps import FleetDep, Operator, SessionsDep, Viewer
from server.api.responses import AUTH, BODY, errors
from server.api.schemas import EpisodeOut, Id, SegmentLabelIn, SegmentOut
from server.db import EpisodeRecord, SegmentRecord
from server.labels import LabelChange, set_label
from storage.paths import in_store

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
    path = in_store(fleet.data_dir, row.path)
    if not path.is_file():
        raise HTTPException(410, f"segment {segment_id}'s file is gone")
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.patch(
    "/segments/{segment_id}",
    response_model=SegmentOut,
    responses=errors(AUTH, BODY, 404, why={404: "no such segment"}),
)
def label_segment(segment_id: Id, body: SegmentLabelIn, sessions: SessionsDep, who: Operator) -> SegmentOut:
    """Labels a takeover good or bad, discards it (kept on disk, never trained on) or notes it; records
    who did and when. Only the fields sent change."""
    given = body.model_fields_set
    change = LabelChange(
        label=body.label if "label" in given else None,
        clear_label="label" in given and body.label is None,
        discarded=body.discarded if "discarded" in given else None,
        note=body.note if "note" in given else None,
    )
    return SegmentOut.model_validate(set_label(sessions, segment_id, who.name, change))

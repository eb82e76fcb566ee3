"""``/finetune-jobs``: fine-tuning jobs with their status, progress, data, evaluation and gate decision;
an admin can start one (``hitl finetune`` in a separate, low-priority process)."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy import select

from server.api.deps import Admin, SessionsDep, Viewer
from server.api.responses import AUTH, BODY, errors
from server.api.schemas import FinetuneJobIn, FinetuneJobOut, FinetuneScheduleOut, Id, PolicyName
from server.db import FinetuneJob
from server.errors import ServiceError
from server.finetune.job import FinetuneRunner
from server.finetune.plan import JobRequest, parse_since
from server.finetune.scheduler import JobLauncher

router = APIRouter(tags=["fine-tuning"])


def get_launcher(request: Request) -> JobLauncher:
    return request.app.state.launcher


LauncherDep = Annotated[JobLauncher, Depends(get_launcher)]


@router.get("/finetune-jobs", response_model=list[FinetuneJobOut], responses=errors(AUTH, 422))
def jobs(
    sessions: SessionsDep,
    _: Viewer,
    lineage: PolicyName | None = None,
    status: Literal["queued", "running", "succeeded", "failed", "interrupted"] | None = None,
    limit: int = Query(50, ge=1, le=1000),
) -> list[FinetuneJob]:
    """The newest jobs first."""
    q = select(FinetuneJob).order_by(FinetuneJob.id.desc()).limit(limit)
    if lineage is not None:
        q = q.where(FinetuneJob.lineage == lineage)
    if status is not None:
        q = q.where(FinetuneJob.status == status)
    with sessions() as s:
        return list(s.scalars(q))


@router.get("/finetune-schedule", response_model=FinetuneScheduleOut, responses=errors(AUTH))
def schedule(request: Request, _: Viewer) -> FinetuneScheduleOut:
    """When the nightly job runs next, and whether one started by this service is running."""
    status = request.app.state.schedule_status()  # server.finetune.scheduler.ScheduleStatus
    return FinetuneScheduleOut(**dataclasses.asdict(status))


@router.get("/finetune-jobs/{job_id}", response_model=FinetuneJobOut, responses=errors(AUTH, 404, 422))
def job(job_id: Id, sessions: SessionsDep, _: Viewer) -> FinetuneJob:
    with sessions() as s:
        row = s.get(FinetuneJob, job_id)
    if row is None:
        raise ServiceError(404, f"no fine-tuning job {job_id}")
    return row


@router.post(
    "/finetune-jobs",
    response_model=FinetuneJobOut,
    status_code=202,
    responses=errors(
        AUTH,
        BODY,
        404,
        409,
        why={
            404: "no such policy or version",
            409: "a job started by this service is still running",
            422: "the request does not validate, or the lineage has no takeover data",
        },
    ),
)
def start_job(body: FinetuneJobIn, request: Request, sessions: SessionsDep, launcher: LauncherDep, _: Admin):
    """Queues a job for ``policy`` and starts it in a separate process; poll ``/finetune-jobs/{id}``.
    The policy and its data are checked first: a bad request queues nothing."""
    try:
        since = parse_since(body.since) if body.since else None
    except ValueError as exc:
        raise ServiceError(422, str(exc)) from exc
    runner = FinetuneRunner(sessions, request.app.state.settings.data_dir, progress=False)
    [plan] = runner.plan(JobRequest(policy=body.policy, since=since))
    if launcher.running():
        raise ServiceError(409, "a fine-tuning job started by this service is still running")
    with sessions() as s:
        row = FinetuneJob(lineage=plan.lineage, status="queued", trigger="api", parent_id=plan.parent.id)
        s.add(row)
        s.commit()
    extra = ["--since", body.since.strip()] if body.since else []

    def exited(code: int, log_file) -> None:  # a process that died before taking its queued row
        runner.fail_queued(row.id, f"the job process exited with code {code} before starting; see {log_file}")

    if launcher.launch("api", body.policy, row.id, extra, on_exit=exited) is None:
        with sessions() as s:
            s.delete(s.get(FinetuneJob, row.id))
            s.commit()
        raise ServiceError(409, "a fine-tuning job started by this service is still running")
    with sessions() as s:
        return s.get(FinetuneJob, row.id)

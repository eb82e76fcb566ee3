"""The fine-tuning job: from a lineage's active version and its operators' takeovers to a new version,
recalibrated, evaluated and put through the promotion gate, all recorded in the registry.

One job at a time, across processes and machines: the job holds the database lease ``finetune``
(``server.lease``) from start to end, renewed by a heartbeat. Its writes to the registry (the new
version, its promotion) are fenced: each commits in the transaction that renews the lease, or not at
all. A job that is interrupted (killed, crashed, lease lost) leaves its row ``running`` or
``interrupted`` and its training state in ``work_dir``; the next run for the same lineage, parent
and data resumes it from its last checkpoint.

Bad input is refused before anything is written (``server.finetune.plan``: the request, and the plan
that finds each job's parent version and takeover segments). This module runs the plans: the lease,
the job's row (opened, resumed or superseded; failed or interrupted when a stage raises), and the
job's seven stages in order (``server.finetune.stages``), given what they need of the runner
(``server.finetune.context.JobContext``).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from server import lease as leases
from server.db import FinetuneJob, utcnow
from server.errors import ServiceError
from server.finetune.context import JobContext
from server.finetune.plan import JobRequest, Plan, parse_since, plan_jobs, select_segments
from server.finetune.stages import JobRun, update_job

__all__ = ["FinetuneRunner", "JobBusy", "JobRequest", "Plan", "parse_since"]

log = logging.getLogger("hitl.finetune")


class JobBusy(RuntimeError):
    """Another job holds the lease."""


class FinetuneRunner:
    """Runs fine-tuning jobs against the metadata store ``sessions`` and the data folder ``data_dir``.
    eval_tasks: lineage -> target tasks (the settings' ``finetune.eval_tasks``)."""

    def __init__(
        self,
        sessions: sessionmaker,
        data_dir: str | Path,
        eval_tasks: dict[str, list[str]] | None = None,
        progress: bool = True,
        report: Callable[[str], None] = lambda line: log.info("%s", line),
    ) -> None:
        self.sessions = sessions
        self.data_dir = Path(data_dir).resolve()
        self.eval_tasks = eval_tasks or {}
        self.progress = progress
        self.report = report
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"

    @property
    def context(self) -> JobContext:
        """What the job's stages are given of this runner."""
        return JobContext(self.sessions, self.data_dir, self.eval_tasks, self.progress, self.report)

    def plan(self, request: JobRequest) -> list[Plan]:
        """The jobs a request would run (``server.finetune.plan.plan_jobs``): validation only, nothing written."""
        return plan_jobs(self.sessions, request)

    # -- running -------------------------------------------------------------------------------------------
    def run(self, request: JobRequest) -> list[dict]:
        """Plans, then runs one job per lineage under the lease; returns each job's summary.
        Raises ServiceError for bad input and JobBusy when another job holds the lease."""
        try:
            plans = self.plan(request)
        except ServiceError as exc:
            if request.job_id is not None:
                self.fail_queued(request.job_id, exc.message)
            raise
        if not plans:
            if request.job_id is not None:
                self.fail_queued(request.job_id, "no lineage has new takeover segments")
            self.report("nothing to do: no lineage has new closed or recovered takeover segments")
            return []
        lease = leases.acquire(self.sessions, leases.FINETUNE_LEASE, self.owner, request.lease_ttl)
        if lease is None:
            owner, left = leases.holder(self.sessions, leases.FINETUNE_LEASE)
            if request.job_id is not None:
                self.fail_queued(request.job_id, f"another fine-tuning job is running ({owner})")
            raise JobBusy(f"another fine-tuning job holds the lease: {owner}, {left or 0:.0f} s left unless renewed")
        out = []
        try:
            with leases.Heartbeat(self.sessions, lease) as beat:
                for plan in plans:
                    out.append(self._run_one(plan, request, beat))
        finally:
            leases.release(self.sessions, lease)
        return out

    def fail_queued(self, job_id: int, error: str) -> None:
        """Ends a job row that is still ``queued`` (its process never took it); others are left alone."""
        with self.sessions() as s:
            job = s.get(FinetuneJob, job_id)
            if job is not None and job.status == "queued":
                job.status, job.error, job.ended_at = "failed", error[:4000], utcnow()
                s.commit()

    def _job_row(self, plan: Plan, request: JobRequest) -> tuple[int, bool]:
        """(job id, resumed): an unfinished job of the lineage on the same parent and data is resumed; other
        unfinished ones (their holder is gone: we hold the lease) are marked interrupted."""
        config = request.config_for(plan.lineage)
        key = {
            "segment_ids": plan.segment_ids,
            # the selection's choice too: a takeover whose episode has ended since must not resume old training
            "selected_segment_ids": [s.id for s in select_segments(self.sessions, plan.segments, config.selection)[0]],
            "source": request.source,
            "episodes": str(plan.episodes or ""),
            "pretrain_data": str(request.pretrain_data or ""),
            "train_config": {k: v for k, v in config.to_dict().items() if not k.startswith("eval")},
        }
        with self.sessions() as s:
            stale = list(
                s.scalars(
                    select(FinetuneJob)
                    .where(FinetuneJob.lineage == plan.lineage, FinetuneJob.status.in_(("running", "interrupted")))
                    .order_by(FinetuneJob.id.desc())
                )
            )
            resumable = None
            for job in stale:
                same = job.parent_id == plan.parent.id and {k: (job.data or {}).get(k) for k in key} == key
                if resumable is None and same and job.work_dir:
                    resumable = job
                    continue
                # superseded: other data or settings; it can never resume, so its checkpoints go
                job.status, job.ended_at = "interrupted", job.ended_at or utcnow()
                job.error = f"superseded by a run on other data or settings ({job.error or 'not finished'})"[:4000]
                if job.work_dir:
                    shutil.rmtree(self.data_dir / job.work_dir / "train", ignore_errors=True)
            queued = s.get(FinetuneJob, request.job_id) if request.job_id is not None else None
            if resumable is not None:
                job, resumed = resumable, True
                if queued is not None and queued.id != job.id:
                    queued.status, queued.ended_at = "failed", utcnow()
                    queued.error = f"resumes job {job.id} instead"
            elif queued is not None and queued.status == "queued":
                job, resumed = queued, False
            else:
                job, resumed = FinetuneJob(lineage=plan.lineage), False
                s.add(job)
            job.status, job.stage, job.parent_id = "running", "data", plan.parent.id
            job.source, job.trigger = request.source, job.trigger if resumed else request.trigger
            job.since = datetime.now(UTC) - request.since if request.since else None
            job.command = job.command or request.command
            job.started_at = job.started_at or utcnow()
            job.ended_at, job.error = None, None
            job.data = {**(job.data or {}), **key, "resumes": (job.data or {}).get("resumes", 0) + int(resumed)}
            s.commit()
            if not job.work_dir:
                job.work_dir = str(Path("finetune") / f"job-{job.id}")
                s.commit()
            return job.id, resumed

    def _update(self, job_id: int, **values) -> None:
        update_job(self.sessions, job_id, **values)

    def _run_one(self, plan: Plan, request: JobRequest, beat: leases.Heartbeat) -> dict:
        job_id, resumed = self._job_row(plan, request)
        self.report(f"job {job_id}: fine-tuning {plan.parent.ref}" + (" (resuming)" if resumed else ""))
        try:
            summary = self._work(job_id, plan, request, beat)
        except leases.LeaseLost:
            raise  # another holder now owns the job's lineage: write nothing more
        except (KeyboardInterrupt, SystemExit):
            self._update(job_id, status="interrupted", error="interrupted", ended_at=utcnow())
            raise
        except Exception as exc:  # noqa: BLE001 - the job's failure is recorded, then the next lineage runs
            log.exception("job %d failed", job_id)
            self._update(job_id, status="failed", error=f"{type(exc).__name__}: {exc}"[:4000], ended_at=utcnow())
            return {"job": job_id, "lineage": plan.lineage, "status": "failed", "error": str(exc)}
        return summary

    def _work(self, job_id: int, plan: Plan, request: JobRequest, beat: leases.Heartbeat) -> dict:
        """One job's seven stages (``server.finetune.stages``), in order; returns its summary, also
        reported as one JSON line."""
        job = JobRun.prepare(self.context, job_id, plan, request, beat)
        data = job.collect_data()
        trained = job.train(data)
        candidate = job.write_candidate(data, trained)
        calibration = job.recalibrate(data, trained, candidate)
        evaluation = job.evaluate_candidate(data, trained)
        summary = job.register(data, candidate, calibration, evaluation)
        self.report(json.dumps(summary))
        return summary

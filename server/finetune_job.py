"""The fine-tuning job: from a lineage's active version and its operators' takeovers to a new version,
recalibrated, evaluated and put through the promotion gate, all recorded in the registry.

One job at a time, across processes and machines: the job holds the database lease ``finetune``
(``server.lease``) from start to end, renewed by a heartbeat. Its writes to the registry (the new
version, its promotion) are fenced: each commits in the transaction that renews the lease, or not at
all. A job that is interrupted (killed, crashed, lease lost) leaves its row ``running`` or
``interrupted`` and its training state in ``work_dir``; the next run for the same lineage, parent
and data resumes it from its last checkpoint.

Bad input is refused before anything is written: a reference that names no version, a lineage with
no closed or recovered takeover segments. A segment that cannot be read is skipped and named in the
job's ``data.skipped`` with its reason; a job left with no usable sample fails with that list.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from policy.checkpoint import load_calibration, load_policy, read_info, save_calibration, save_policy
from policy.finetune import (
    FinetuneConfig,
    FinetuneDataError,
    TaskResult,
    evaluate,
    finetune_policy,
    gate,
    pretraining_split,
)
from server import lease as leases
from server import registry
from server.db import EpisodeRecord, FinetuneJob, PolicyVersion, SegmentRecord, utcnow
from server.errors import ServiceError
from server.recording import resolve
from storage import keys
from storage.dataset import DatasetConfig, load_dataset
from storage.takeovers import TakeoverSelection, load_takeovers

log = logging.getLogger("hitl.finetune")

SOURCES = ("takeovers", "full-episodes")
USABLE = ("closed", "recovered")  # open segments are never used
_SINCE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhdw])\s*$")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 604800}


def parse_since(text: str) -> timedelta:
    """``30m``, ``24h``, ``7d``, ``2w`` as a timedelta (ValueError otherwise)."""
    m = _SINCE.match(text or "")
    if m is None or float(m[1]) <= 0:
        raise ValueError(f"--since {text!r}: expected a positive duration like 30m, 24h, 7d or 2w")
    try:
        return timedelta(seconds=float(m[1]) * _UNITS[m[2]])
    except OverflowError as exc:
        raise ValueError(f"--since {text!r}: too long") from exc


class JobBusy(RuntimeError):
    """Another job holds the lease."""


@dataclass(frozen=True)
class JobRequest:
    """policy: NAME, NAME@active or NAME@VERSION (None: every lineage with new takeover segments);
    since: only segments that ended this recently; source: ``takeovers`` or ``full-episodes`` (then
    ``episodes``: a folder of episode MCAPs); eval_tasks: the gate's target tasks (default: the tasks the
    takeovers came from); promote: promote a version that passes the gate; job_id: a queued job row to
    run (the API's trigger)."""

    policy: str | None = None
    since: timedelta | None = None
    source: str = "takeovers"
    episodes: Path | None = None
    pretrain_data: Path | None = None
    eval_tasks: tuple[str, ...] | None = None
    promote: bool = True
    config: FinetuneConfig = field(default_factory=FinetuneConfig)
    trigger: str = "cli"
    command: str | None = None
    job_id: int | None = None
    lease_ttl: float = 60.0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.source == "full-episodes" and self.episodes is None:
            raise ValueError("--source full-episodes needs --episodes DIR (a folder of episode MCAP files)")
        if self.source == "full-episodes" and self.policy is None:
            raise ValueError("--source full-episodes needs --policy")


@dataclass
class Plan:
    """What one job will use: the parent version, and the segment rows or episode folder."""

    lineage: str
    parent: PolicyVersion
    segments: list[SegmentRecord]
    episodes: Path | None = None

    @property
    def segment_ids(self) -> list[int]:
        return [s.id for s in self.segments]


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

    # -- planning: validation only, nothing written --------------------------------------------------------
    def plan(self, request: JobRequest) -> list[Plan]:
        if request.policy is not None:
            parent = registry.resolve(self.sessions, request.policy)
            if request.source == "full-episodes":
                if not Path(request.episodes).is_dir():
                    raise ServiceError(422, f"--episodes {request.episodes}: no such folder")
                return [Plan(parent.name, parent, [], Path(request.episodes))]
            segments = self._segments(parent.name, request.since)
            if not segments:
                window = f" that ended in the last {request.since}" if request.since else ""
                raise ServiceError(
                    422, f"policy {parent.name} has no closed or recovered takeover segments{window}: nothing to learn"
                )
            return [Plan(parent.name, parent, segments)]
        plans = []
        for name, active in sorted(registry.active_versions(self.sessions).items()):
            segments = self._segments(name, request.since)
            # new: not in the manifest of any version of the lineage (a candidate the gate refused included,
            # so a refused run is not repeated every night on the same data)
            used = {
                i
                for v in registry.versions(self.sessions, name)
                for key in ("segment_ids", "skipped_segment_ids", "excluded_segment_ids")
                for i in (v.manifest or {}).get(key, [])
            }
            # news: what the selection would learn from (a takeover it leaves out starts no job; one whose
            # episode is still running is news once its episode has ended, if it succeeded)
            kept = {s.id for s in self._select(segments, request.config.selection)[0]}
            if any(s.id not in used and s.id in kept for s in segments):
                plans.append(Plan(name, active, segments))
        return plans

    def _select(
        self, segments: list[SegmentRecord], selection: TakeoverSelection
    ) -> tuple[list[SegmentRecord], dict[int, str], list[SegmentRecord]]:
        """(kept, left out {segment id: why}, waiting: those whose episode has not ended) under
        ``selection``; with ``successful_only``, by the outcome of each segment's episode."""
        if not selection.successful_only:
            return list(segments), {}, []
        ids = {s.episode_id for s in segments if s.episode_id is not None}
        with self.sessions() as db:
            rows = db.execute(select(EpisodeRecord.id, EpisodeRecord.outcome).where(EpisodeRecord.id.in_(ids)))
            outcomes = {i: outcome for i, outcome in rows}
        kept, left_out, waiting = [], {}, []
        for seg in segments:
            if seg.episode_id not in outcomes:
                left_out[seg.id] = "no episode recorded for it (successful episodes only)"
            elif outcomes[seg.episode_id] is None:
                waiting.append(seg)
            elif (why := selection.why_excluded(outcomes[seg.episode_id])) is not None:
                left_out[seg.id] = why
            else:
                kept.append(seg)
        return kept, left_out, waiting

    def _segments(self, lineage: str, since: timedelta | None) -> list[SegmentRecord]:
        ids = registry.lineage_ids(self.sessions, lineage)
        q = select(SegmentRecord).where(SegmentRecord.policy_id.in_(ids), SegmentRecord.status.in_(USABLE))
        if since is not None:
            q = q.where(SegmentRecord.ended_at >= datetime.now(UTC) - since)
        with self.sessions() as s:
            return list(s.scalars(q.order_by(SegmentRecord.id)))

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
        key = {
            "segment_ids": plan.segment_ids,
            # the selection's choice too: a takeover whose episode has ended since must not resume old training
            "selected_segment_ids": [s.id for s in self._select(plan.segments, request.config.selection)[0]],
            "source": request.source,
            "episodes": str(plan.episodes or ""),
            "pretrain_data": str(request.pretrain_data or ""),
            "train_config": {k: v for k, v in request.config.to_dict().items() if not k.startswith("eval")},
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
        with self.sessions() as s:
            job = s.get(FinetuneJob, job_id)
            for k, v in values.items():
                setattr(job, k, v)
            s.commit()

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
        cfg = request.config
        work = self.data_dir / "finetune" / f"job-{job_id}"
        work.mkdir(parents=True, exist_ok=True)
        parent_dir = Path(plan.parent.path)
        parent, info = load_policy(parent_dir)
        pc = parent.config
        pretrain_folder = Path(request.pretrain_data or info.get("dataset", {}).get("folder", ""))

        # data
        if plan.episodes is not None:
            ds = load_dataset(plan.episodes, DatasetConfig(pc.obs_horizon, pc.action_horizon, val_fraction=0.0))
            if ds.obs.shape[1] != pc.obs_dim:
                raise FinetuneDataError(
                    f"{plan.episodes}: {ds.obs.shape[1]}-dim observations, policy takes {pc.obs_dim}"
                )
            fresh = ds.arrays("all")
            tasks = sorted({m.get("task") for m in ds.meta if m.get("task")})
            manifest_new = {"episodes_folder": str(plan.episodes), "episodes": ds.names, "excluded": ds.excluded}
            counts = {"episodes": ds.num_episodes, "samples": int(len(fresh[keys.OBS]))}
            skipped, excluded = {}, {}
        else:
            selected, left_out, waiting = self._select(plan.segments, cfg.selection)
            excluded = {Path(s.path).name: left_out[s.id] for s in plan.segments if s.id in left_out}
            for name, why in excluded.items():
                self.report(f"job {job_id}: left out segment {name}: {why}")
            for seg in waiting:
                self.report(f"job {job_id}: segment {Path(seg.path).name} waits for its episode to end")
            takeovers = load_takeovers([resolve(self.data_dir, s.path) for s in selected], pc.obs_dim, cfg.selection)
            for name, why in takeovers.skipped.items():
                self.report(f"job {job_id}: skipped segment {name}: {why}")
            fresh = takeovers.arrays(pc.obs_horizon, pc.action_horizon)
            used = set(takeovers.used)
            segs = [s for s in selected if Path(s.path).name in used]
            tasks = sorted({s.task for s in segs})
            manifest_new = {
                "segment_ids": [s.id for s in segs],
                "segments": [s.path for s in segs],
                "skipped": takeovers.skipped,
                "skipped_segment_ids": [s.id for s in selected if Path(s.path).name in takeovers.skipped],
                "excluded": excluded,
                "excluded_segment_ids": sorted(left_out),
            }
            counts = {
                "segments": len(segs),
                "samples": len(takeovers),
                "skipped": len(takeovers.skipped),
                "excluded": len(excluded),
                "waiting": len(waiting),
            }
            skipped = takeovers.skipped
        self._update(
            job_id,
            data={
                **self._data(job_id),
                "counts": counts,
                "skipped": skipped,
                "excluded": excluded,
                "tasks": tasks,
                "pretraining": str(pretrain_folder),
            },
            progress=0.02,
        )
        if not len(fresh[keys.OBS]):
            raise FinetuneDataError(
                f"no usable sample: {len(skipped)} segment(s) skipped, {len(excluded)} left out by the selection, "
                f"{counts.get('waiting', 0)} waiting for their episode to end ("
                + "; ".join(f"{k}: {v}" for k, v in list((skipped | excluded).items())[:5])
                + ")"
            )
        pre_train, _, pre_names = pretraining_split(parent, info, pretrain_folder)

        # training (resumable)
        steps = cfg.steps_for(len(fresh[keys.OBS]))
        self._update(job_id, stage="train")

        def on_checkpoint(state) -> None:
            beat.check()
            self._update(job_id, progress=0.05 + 0.7 * state.step / steps)

        child, history = finetune_policy(parent, fresh, pre_train, cfg, work / "train", self.progress, on_checkpoint)

        # the new version's folder: weights, config (with its manifest), calibration and signals
        beat.check()
        self._update(job_id, stage="calibrate", progress=0.76)
        manifest = {
            "parent": plan.parent.ref,
            "source": request.source,
            "pretraining": {"folder": str(pretrain_folder), "episodes": pre_names, "ratio": 1 - cfg.ratio},
            **manifest_new,
        }
        child_info = {
            **{k: v for k, v in info.items() if k not in ("format", "policy", "normalization")},
            "dataset": {**info.get("dataset", {}), "folder": str(pretrain_folder)},
            "finetune": {
                "job": job_id,
                "config": cfg.to_dict(),
                "manifest": manifest,
                "history": {
                    k: history[k]
                    for k in (
                        "steps",
                        "takeover_samples",
                        "pretraining_samples",
                        "obs_dims_widened",
                        "seconds",
                        "resumed_from_step",
                    )
                },
                "final_train_loss": history["train_loss"][-1] if history["train_loss"] else None,
            },
            "command": request.command,
        }
        out = work / "candidate"
        if out.exists():
            shutil.rmtree(out)
        save_policy(child, out, child_info)
        calibration = self._recalibrate(child, child_info, parent_dir, pretrain_folder, out, cfg)

        # evaluation through the one controller, parent and candidate on the same seeds
        train_task = info.get("task") or plan.parent.task
        targets = list(request.eval_tasks or self.eval_tasks.get(plan.lineage) or tasks or [train_task])
        all_tasks = list(dict.fromkeys([train_task, *targets]))
        self._update(job_id, stage="evaluate", progress=0.8)
        parent_eval = self._parent_eval(plan.parent.id, parent, all_tasks, cfg)
        beat.check()
        child_eval = evaluate(child, all_tasks, cfg.eval_episodes, cfg.eval_seed, self.progress)
        decision = gate(parent_eval, child_eval, train_task, targets, cfg.tolerance, cfg.min_gain)
        evaluation = {"parent": _eval_doc(parent_eval, cfg), "candidate": _eval_doc(child_eval, cfg)}

        # registration, under the lease
        beat.check()
        self._update(job_id, stage="gate", progress=0.98)
        final = self._place(plan.lineage, out)
        status_reason = ("gate passed: " if decision.promote else "gate refused: ") + decision.reason
        row = registry.register(
            self.sessions,
            final,
            plan.parent.task,
            name=plan.lineage,
            parent=plan.parent.id,
            threshold=calibration["threshold"],
            manifest=manifest,
            calibration={k: calibration[k] for k in ("threshold", "quantile", "samples", "episodes", "data")},
            evaluation=evaluation["candidate"],
            command=request.command,
            status_reason=status_reason,
            lease=beat.lease,
        )
        promoted = bool(decision.promote and request.promote)
        if promoted:
            beat.check()
            registry.promote(self.sessions, row.id, status_reason, lease=beat.lease)
        gate_doc = decision.to_dict() | {"promoted": promoted, "auto_promote": request.promote}
        self._update(
            job_id,
            status="succeeded",
            stage="done",
            progress=1.0,
            version_id=row.id,
            evaluation=evaluation,
            gate=gate_doc,
            ended_at=utcnow(),
        )
        shutil.rmtree(work / "train", ignore_errors=True)  # the version is registered: nothing left to resume
        summary = {
            "job": job_id,
            "lineage": plan.lineage,
            "status": "succeeded",
            "parent": plan.parent.ref,
            "version": row.ref,
            "path": str(final),
            "promoted": promoted,
            "gate": decision.reason,
            "data": counts,
            "threshold": calibration["threshold"],
            "evaluation": {
                t: {"parent": parent_eval[t].success_rate, "candidate": child_eval[t].success_rate} for t in all_tasks
            },
        }
        self.report(json.dumps(summary))
        return summary

    def _data(self, job_id: int) -> dict:
        with self.sessions() as s:
            return dict(s.get(FinetuneJob, job_id).data or {})

    def _recalibrate(self, child, info: dict, parent_dir: Path, data: Path, out: Path, cfg: FinetuneConfig) -> dict:
        """The denoising threshold on the held-out validation episodes, and each of the parent's signals
        that calibrates on demonstrations alone; signals with trained models are not carried."""
        from policy.calibrate import calibrate
        from policy.signal_data import demo_data
        from policy.signals import load_signal, save_signal
        from policy.uncertainty import UncertaintyConfig

        parent_cal = load_calibration(parent_dir) or {}
        ucfg = UncertaintyConfig(**parent_cal["uncertainty"]) if parent_cal.get("uncertainty") else None
        record = calibrate(child, info, data, cfg.quantile, ucfg, progress=self.progress)
        save_calibration(out, record)
        carried, dropped = [], {}
        signals = parent_dir / "signals"
        for folder in sorted(signals.iterdir()) if signals.is_dir() else []:
            try:
                signal = load_signal(child, parent_dir, folder.name)
            except Exception as exc:  # noqa: BLE001 - an unusable parent signal is reported, not fatal
                dropped[folder.name] = f"cannot be loaded: {exc}"
                continue
            if signal.has_models or signal.needs_rollouts:
                dropped[folder.name] = f"trains on the policy itself: run `hitl train-signal --signal {folder.name}`"
                continue
            signal.calibrate(demo_data(child, info, data), progress=self.progress)
            save_signal(signal, out, {"command": "hitl finetune (recalibrated on the validation episodes)"})
            carried.append(folder.name)
        record |= {"signals": carried, "signals_not_carried": dropped}
        save_calibration(out, record)
        return record

    def _parent_eval(self, parent_id: int, parent, tasks: list[str], cfg: FinetuneConfig) -> dict[str, TaskResult]:
        """The parent's results on the same seeds: reused from the registry when it has them."""
        with self.sessions() as s:
            known = dict((s.get(PolicyVersion, parent_id).evaluation or {}).get("tasks", {}))
        out, todo = {}, []
        for task in tasks:
            d = known.get(task)
            if d and (d.get("episodes"), d.get("seed")) == (cfg.eval_episodes, cfg.eval_seed):
                out[task] = TaskResult.from_dict(d)
            else:
                todo.append(task)
        if todo:
            out |= evaluate(parent, todo, cfg.eval_episodes, cfg.eval_seed, self.progress)
            with self.sessions() as s:
                row = s.get(PolicyVersion, parent_id)
                merged = dict(row.evaluation or {})
                merged["tasks"] = {**merged.get("tasks", {}), **{t: out[t].to_dict() for t in todo}}
                row.evaluation = merged
                s.commit()
        return out

    def _place(self, lineage: str, candidate: Path) -> Path:
        """Moves the candidate to ``<data_dir>/policies/<lineage>/v<N>`` (N: its version number to be)."""
        with self.sessions() as s:
            last = max(
                [r.version for r in s.scalars(select(PolicyVersion).where(PolicyVersion.name == lineage))], default=0
            )
        n = last + 1
        while True:
            final = self.data_dir / "policies" / lineage / f"v{n}"
            with self.sessions() as s:
                taken = s.scalars(select(PolicyVersion.id).where(PolicyVersion.path == str(final.resolve()))).first()
            if taken is None:
                break
            n += 1  # a folder of that name is registered (another lineage layout): never overwritten
        if final.exists():  # left by a job that crashed between placing and registering: not registered
            shutil.rmtree(final)
        final.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(candidate), final)
        read_info(final)
        return final


def _eval_doc(results: dict[str, TaskResult], cfg: FinetuneConfig) -> dict:
    return {"episodes": cfg.eval_episodes, "seed": cfg.eval_seed, "tasks": {t: r.to_dict() for t, r in results.items()}}

"""The seven stages of one fine-tuning job, one method each, run in order by ``FinetuneRunner._work``.

``JobRun.prepare`` (the work folder, the parent, its pretraining folder), ``collect_data``,
``train`` (resumable), ``write_candidate``, ``recalibrate``, ``evaluate_candidate`` (parent and
candidate on the same seeds) and ``register`` (under the lease, promoted when the gate passes). Each
stage records its stage and progress in the job's row and hands what it made to the next ones as a
small frozen dataclass.
The runner (``server.finetune.job``) holds the lease around them and records a stage's failure; the
stages are given what they need of it as a ``JobContext`` (``server.finetune.context``).

Before each write that another job could race (a checkpoint, the candidate, the registration, the
promotion) a stage checks the lease (``Heartbeat.check``): a job that lost it writes nothing more.
A segment that cannot be read is skipped and named in the job's ``data.skipped`` with its reason; a
job left with no usable sample fails with that list.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from policy.checkpoint import check_fits, load_calibration, load_policy, read_info, save_calibration, save_policy
from policy.finetune import (
    FinetuneConfig,
    FinetuneDataError,
    GateDecision,
    TaskResult,
    check_layout,
    evaluate,
    finetune_policy,
    fit_threshold_on_own_episodes,
    gate,
    pretraining_split,
)
from server import lease as leases
from server import registry
from server.db import FinetuneJob, PolicyVersion, utcnow
from server.finetune.context import JobContext
from server.finetune.plan import JobRequest, Plan, select_segments
from sim.demos import DemoRecipe, ensure_demos
from storage import keys, paths
from storage.dataset import DatasetConfig, load_dataset
from storage.obs_layout import recorded
from storage.paths import in_store
from storage.takeovers import load_takeovers

if TYPE_CHECKING:
    import numpy as np

    from policy.diffusion_policy import DiffusionPolicy


def update_job(sessions: sessionmaker, job_id: int, **values) -> None:
    """Sets fields of a job's row."""
    with sessions() as s:
        job = s.get(FinetuneJob, job_id)
        for k, v in values.items():
            setattr(job, k, v)
        s.commit()


@dataclass(frozen=True)
class JobData:
    """The new samples (``arrays``: {OBS, ACTION} windows), the tasks they came from, and what the
    manifest (``manifest``) and the job's row (``counts``, ``skipped``, ``excluded``) record of them."""

    arrays: dict[str, np.ndarray]
    tasks: list[str]
    manifest: dict
    counts: dict
    skipped: dict[str, str]
    excluded: dict[str, str]


@dataclass(frozen=True)
class Trained:
    """The fine-tuned policy, its training history, the pretraining episodes it was mixed with, those of
    the policy's that were left out (name: why) and how they were identified (``policy.heldout``)."""

    policy: DiffusionPolicy
    history: dict
    pretraining_episodes: list[str]
    pretraining_left_out: dict[str, str] = field(default_factory=dict)
    pretraining_checked: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Candidate:
    """The new version's folder (not placed yet), its config.json and its manifest."""

    folder: Path
    info: dict
    manifest: dict


@dataclass(frozen=True)
class Evaluation:
    """Parent and candidate on the same tasks and seeds, the gate's decision, and the record of both."""

    tasks: list[str]  # the training task, then the target tasks
    parent: dict[str, TaskResult]
    candidate: dict[str, TaskResult]
    decision: GateDecision
    doc: dict  # {"parent": ..., "candidate": ...}: what the job's row and the registry record


def _record_pretraining(info: dict, folder: Path, progress: bool, report: Callable[[str], None], job_id: int) -> None:
    """Records the parent's pretraining demonstrations where its config.json says they go, seeded as
    its recipe says, when this machine lacks them (a fresh clone: ``data/`` is not in the repository).
    A parent without a recipe (trained before recipes, or on data ``hitl demos`` did not make) needs
    the folder, or ``--pretrain-data``: ``pretraining_split`` then says so."""
    doc = info.get("dataset", {}).get("recipe")
    if doc is None:
        return
    try:
        recipe = DemoRecipe.from_dict(doc)
    except ValueError as exc:
        raise FinetuneDataError(
            f"the policy's config.json holds an unusable recipe for its pretraining data: {exc}"
        ) from None
    missing = [f for f in recipe.files(folder) if not f.is_file()]
    if missing:
        report(
            f"job {job_id}: recording {len(missing)} of the {recipe.episodes} pretraining episodes into "
            f"{paths.portable(folder)} ({recipe.command(paths.portable(folder))})"
        )
        # as many recording processes as the job has threads (``[finetune] threads``): robosuite uses one core
        ensure_demos(recipe, folder, progress=progress, workers=max(1, torch.get_num_threads()))


@dataclass(frozen=True)
class JobRun:
    """One job: its row, plan, request and lease, the runner's store and reporting (its ``JobContext``), and
    what ``prepare`` set up. Each stage is a method; what it makes, the next stages are given."""

    id: int
    plan: Plan
    request: JobRequest
    beat: leases.Heartbeat
    sessions: sessionmaker
    data_dir: Path
    eval_tasks: dict[str, list[str]]  # lineage -> the gate's target tasks (the settings')
    progress: bool
    report: Callable[[str], None]
    work: Path  # <data_dir>/finetune/job-<id>: the training state (train/) and the candidate's folder
    parent_dir: Path
    parent: DiffusionPolicy
    info: dict  # the parent's config.json
    pretrain_folder: Path  # the parent's pretraining data: --pretrain-data, else what its config.json records

    @property
    def cfg(self) -> FinetuneConfig:
        return self.request.config_for(self.plan.lineage)

    def _update(self, **values) -> None:
        update_job(self.sessions, self.id, **values)

    @classmethod
    def prepare(cls, ctx: JobContext, job_id: int, plan: Plan, request: JobRequest, beat: leases.Heartbeat) -> JobRun:
        """The job's work folder, its parent policy loaded, and the folder of the parent's pretraining
        data: ``--pretrain-data``, else the one its config.json records (a relative one is relative to
        the data root, ``storage.paths``)."""
        work = ctx.data_dir / "finetune" / f"job-{job_id}"
        work.mkdir(parents=True, exist_ok=True)
        parent_dir = registry.folder(plan.parent)
        parent, info = load_policy(parent_dir)
        recorded = info.get("dataset", {}).get("folder", "")
        pretrain_folder = Path(request.pretrain_data) if request.pretrain_data else paths.resolve(recorded)
        return cls(
            id=job_id,
            plan=plan,
            request=request,
            beat=beat,
            sessions=ctx.sessions,
            data_dir=ctx.data_dir,
            eval_tasks=ctx.eval_tasks,
            progress=ctx.progress,
            report=ctx.report,
            work=work,
            parent_dir=parent_dir,
            parent=parent,
            info=info,
            pretrain_folder=pretrain_folder,
        )

    def collect_data(self) -> JobData:
        """The new samples: the episodes of ``--source full-episodes``, or the selected takeover segments
        (those left out, waiting, unreadable or of another observation layout reported); recorded in the job's
        row. FinetuneDataError when no usable sample is left or the episodes are of another observation layout
        than the parent's; CheckpointError when the parent cannot run a task the gate evaluates it on."""
        plan, cfg, pc = self.plan, self.cfg, self.parent.config
        if plan.episodes is not None:
            ds = load_dataset(plan.episodes, DatasetConfig(pc.obs_horizon, pc.action_horizon, val_fraction=0.0))
            check_layout(zip(ds.names, ds.meta, strict=True), self.info, plan.episodes)
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
            selected, left_out, waiting = select_segments(self.sessions, plan.segments, cfg.selection)
            excluded = {Path(s.path).name: left_out[s.id] for s in plan.segments if s.id in left_out}
            for name, why in excluded.items():
                self.report(f"job {self.id}: left out segment {name}: {why}")
            for seg in waiting:
                self.report(f"job {self.id}: segment {Path(seg.path).name} waits for its episode to end")
            files, seen = [in_store(self.data_dir, s.path) for s in selected], [c.name for c in pc.cameras]
            takeovers = load_takeovers(files, pc.obs_dim, cfg.selection, recorded(self.info), seen)  # and its frames
            for name, why in takeovers.skipped.items():
                self.report(f"job {self.id}: skipped segment {name}: {why}")
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
                "labels": {str(s.id): s.label for s in segs if s.label is not None},  # operators' verdicts used
            }
            counts = {
                "segments": len(segs),
                "samples": len(takeovers),
                "skipped": len(takeovers.skipped),
                "excluded": len(excluded),
                "waiting": len(waiting),
            }
            skipped = takeovers.skipped
        with self.sessions() as s:
            known = dict(s.get(FinetuneJob, self.id).data or {})
        self._update(
            data={
                **known,
                "counts": counts,
                "skipped": skipped,
                "excluded": excluded,
                "tasks": tasks,
                "pretraining": paths.portable(self.pretrain_folder),
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
        train_task, targets = self._tasks(tasks)
        for task in dict.fromkeys([train_task, *targets]):  # before training: the gate rolls it out on each
            check_fits(self.info, task, self.plan.parent.ref)
        return JobData(fresh, tasks, manifest_new, counts, skipped, excluded)

    def train(self, data: JobData) -> Trained:
        """The parent fine-tuned on the new samples mixed with its pretraining split, resumable: a training
        state is kept in the work folder at each checkpoint, after the lease is checked. On a machine
        without the pretraining data, it is recorded first (once there are samples to train on)."""
        if not self.request.pretrain_data:
            _record_pretraining(self.info, self.pretrain_folder, self.progress, self.report, self.id)
        pre = pretraining_split(self.parent, self.info, self.pretrain_folder)
        steps = self.cfg.steps_for(len(data.arrays[keys.OBS]))
        self._update(stage="train")

        def on_checkpoint(state) -> None:
            self.beat.check()
            self._update(progress=0.05 + 0.7 * state.step / steps)

        child, history = finetune_policy(
            self.parent, data.arrays, pre.train, self.cfg, self.work / "train", self.progress, on_checkpoint
        )
        return Trained(child, history, pre.train_names, pre.left_out, pre.checked)

    def write_candidate(self, data: JobData, trained: Trained) -> Candidate:
        """The new version's folder in the work folder: its weights, and a config.json with its manifest
        (the parent, the data, the pretraining share; folders as ``storage.paths.portable`` records them)
        and its training history."""
        self.beat.check()
        self._update(stage="calibrate", progress=0.76)
        cfg, info, history = self.cfg, self.info, trained.history
        pretrain_folder = paths.portable(self.pretrain_folder)
        manifest = {
            "parent": self.plan.parent.ref,
            "source": self.request.source,
            "pretraining": {
                "folder": pretrain_folder,
                "episodes": trained.pretraining_episodes,
                "left_out": trained.pretraining_left_out,
                "checked": trained.pretraining_checked,
                "ratio": 1 - cfg.ratio,
            },
            **data.manifest,
        }
        child_info = {
            **{k: v for k, v in info.items() if k not in ("format", "policy", "normalization")},
            "dataset": {**info.get("dataset", {}), "folder": pretrain_folder},
            "finetune": {
                "job": self.id,
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
            "command": self.request.command,
        }
        out = self.work / "candidate"
        if out.exists():
            shutil.rmtree(out)
        save_policy(trained.policy, out, child_info)
        return Candidate(out, child_info, manifest)

    def _tasks(self, data_tasks: list[str]) -> tuple[str, list[str]]:
        """The lineage's training task, and the target tasks the gate compares on: those named for the
        run or the lineage, else the tasks its takeovers came from."""
        train_task = self.info.get("task") or self.plan.parent.task
        targets = self.request.eval_tasks or self.eval_tasks.get(self.plan.lineage) or data_tasks or [train_task]
        return train_task, list(targets)

    def recalibrate(self, job_data: JobData, trained: Trained, candidate: Candidate) -> dict:
        """The denoising threshold on the held-out validation episodes, and each of the parent's signals
        that calibrates on demonstrations alone; signals with trained models are not carried. A signal
        fitted on episodes then has its thresholds fitted on the candidate's own episodes: the training task's
        (a familiar scene) and the target tasks' (new ones), seeds apart from the gate's
        (``policy.finetune.fit_threshold_on_own_episodes``)."""
        from policy.calibrate import calibrate
        from policy.signal_data import demo_data
        from policy.signals import load_signal, save_signal
        from policy.uncertainty import UncertaintyConfig

        child, info, out = trained.policy, candidate.info, candidate.folder
        data, parent_dir = self.pretrain_folder, self.parent_dir
        parent_cal = load_calibration(parent_dir) or {}
        ucfg = UncertaintyConfig(**parent_cal["uncertainty"]) if parent_cal.get("uncertainty") else None
        record = calibrate(child, info, data, self.cfg.quantile, ucfg, progress=self.progress).to_dict()
        save_calibration(out, record)
        carried, dropped, fitted = [], {}, {}
        cfg, (train_task, targets) = self.cfg, self._tasks(job_data.tasks)
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
            if signal.fits_on_episodes:  # the training task is its familiar scene, the target tasks new ones
                fitted[folder.name] = {}
                for scene, tasks in (("familiar", [train_task]), ("new", [t for t in targets if t != train_task])):
                    if tasks:
                        self.beat.check()
                        fitted[folder.name][scene] = fit_threshold_on_own_episodes(
                            child, signal, folder.name, tasks, scene, cfg.fit_episodes, cfg.fit_seed, self.progress
                        )
            save_signal(signal, out, {"command": "hitl finetune (recalibrated on the validation episodes)"})
            carried.append(folder.name)
        record |= {"signals": carried, "signals_not_carried": dropped, "signals_fitted_on_own_episodes": fitted}
        save_calibration(out, record)
        return record

    def evaluate_candidate(self, data: JobData, trained: Trained) -> Evaluation:
        """Parent and candidate through the one controller on the same seeds, on the training task and the
        target tasks, and the promotion gate's decision."""
        cfg = self.cfg
        train_task, targets = self._tasks(data.tasks)
        all_tasks = list(dict.fromkeys([train_task, *targets]))
        self._update(stage="evaluate", progress=0.8)
        parent_eval = self._parent_eval(all_tasks)
        self.beat.check()
        child_eval = evaluate(trained.policy, all_tasks, cfg.eval_episodes, cfg.eval_seed, self.progress)
        decision = gate(parent_eval, child_eval, train_task, targets, cfg.tolerance, cfg.min_gain)
        doc = {"parent": _eval_doc(parent_eval, cfg), "candidate": _eval_doc(child_eval, cfg)}
        return Evaluation(all_tasks, parent_eval, child_eval, decision, doc)

    def register(self, data: JobData, candidate: Candidate, calibration: dict, evaluation: Evaluation) -> dict:
        """Under the lease: the candidate placed and registered, promoted when it passed the gate (and the
        request allows it), the job's row closed as succeeded; returns the job's summary."""
        plan, request, beat, decision = self.plan, self.request, self.beat, evaluation.decision
        beat.check()
        self._update(stage="gate", progress=0.98)
        final = self._place(candidate.folder)
        status_reason = ("gate passed: " if decision.promote else "gate refused: ") + decision.reason
        row = registry.register(
            self.sessions,
            final,
            plan.parent.task,
            name=plan.lineage,
            parent=plan.parent.id,
            threshold=calibration["threshold"],
            manifest=candidate.manifest,
            calibration={k: calibration[k] for k in ("threshold", "quantile", "samples", "episodes", "data")},
            evaluation=evaluation.doc["candidate"],
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
            status="succeeded",
            stage="done",
            progress=1.0,
            version_id=row.id,
            evaluation=evaluation.doc,
            gate=gate_doc,
            ended_at=utcnow(),
        )
        shutil.rmtree(self.work / "train", ignore_errors=True)  # the version is registered: nothing left to resume
        return {
            "job": self.id,
            "lineage": plan.lineage,
            "status": "succeeded",
            "parent": plan.parent.ref,
            "version": row.ref,
            "path": str(final),
            "promoted": promoted,
            "gate": decision.reason,
            "data": data.counts,
            "threshold": calibration["threshold"],
            "evaluation": {
                t: {"parent": evaluation.parent[t].success_rate, "candidate": evaluation.candidate[t].success_rate}
                for t in evaluation.tasks
            },
        }

    def _parent_eval(self, tasks: list[str]) -> dict[str, TaskResult]:
        """The parent's results on the same seeds: reused from the registry when it has them."""
        cfg, parent_id = self.cfg, self.plan.parent.id
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
            out |= evaluate(self.parent, todo, cfg.eval_episodes, cfg.eval_seed, self.progress)
            with self.sessions() as s:
                row = s.get(PolicyVersion, parent_id)
                merged = dict(row.evaluation or {})
                merged["tasks"] = {**merged.get("tasks", {}), **{t: out[t].to_dict() for t in todo}}
                row.evaluation = merged
                s.commit()
        return out

    def _place(self, candidate: Path) -> Path:
        """Moves the candidate to ``<data_dir>/policies/<lineage>/v<N>`` (N: its version number to be)."""
        lineage = self.plan.lineage
        with self.sessions() as s:
            last = max(
                [r.version for r in s.scalars(select(PolicyVersion).where(PolicyVersion.name == lineage))], default=0
            )
        n = last + 1
        while True:
            final = self.data_dir / "policies" / lineage / f"v{n}"
            with self.sessions() as s:
                taken = registry.by_path(s, final)
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

"""Policy slots: a policy version loaded for serving (weights, trace, signals, threshold) with the
controller that drives its robots.

``load_slot`` does the slow part (reading the checkpoint, tracing, loading every signal) and touches
no fleet state, so the fleet calls it outside its lock; swapping a slot in is then one assignment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from policy.checkpoint import CheckpointError, check_fits, load_calibration, load_policy
from policy.controller import Controller
from policy.devices import prepare_for_serving
from policy.diffusion_policy import DiffusionPolicy
from policy.signals import SignalError, load_signal
from server.errors import ServiceError
from server.inference import make_inference
from server.settings import Settings
from sim.registry import make_task

log = logging.getLogger("hitl.server")


@dataclass
class PolicySlot:
    """version: the ``PolicyVersion`` row's id; lineage: its name (``server.registry``); threshold: the
    paper's denoising metric's threshold (what U is drawn against, and the registry row's ``threshold``),
    not the asking signal's (``asking_threshold``); controller: the one control step of this version's
    robots."""

    version: int
    path: Path
    task: str
    policy: DiffusionPolicy
    threshold: float
    controller: Controller
    lineage: str = ""

    @property
    def asking(self) -> str:
        """The asking signal's name ("" when none asks)."""
        return self.controller.asking or ""

    @property
    def asking_threshold(self) -> float | None:
        """The asking signal's threshold: what its score is compared with to ask (None when none asks)."""
        if not self.asking:
            return None
        try:
            return float(self.controller.signals[self.asking].threshold)
        except (KeyError, SignalError):  # not calibrated: the controller refuses such a signal to ask
            return None


def load_slot(settings: Settings, path: Path, task: str, version: int, lineage: str = "") -> PolicySlot:
    """The policy folder ``path`` ready to serve ``task`` (ServiceError 422 naming what is wrong: a folder
    that cannot be read, a checkpoint that cannot run the task, ``policy.checkpoint.check_fits``, a device
    this machine lacks, a signal that is not ready)."""
    try:
        policy, info = load_policy(path)
    except CheckpointError as exc:
        raise ServiceError(422, f"policy {path}: {exc}") from exc
    try:
        check_fits(info, task, path)  # its observation layout, action size and chunking against the task's
    except CheckpointError as exc:
        raise ServiceError(422, str(exc)) from exc
    except KeyError as exc:  # no such task
        raise ServiceError(422, exc.args[0]) from exc
    spec = make_task(task)
    try:
        prepare_for_serving(policy, settings.inference.device, settings.inference.trace_policies)
    except ValueError as exc:  # this machine lacks the device
        raise ServiceError(422, f"policy {path}: {exc}") from exc
    signals = {}
    ctl = settings.controller
    for name in dict.fromkeys([ctl.signal, "denoising", *ctl.shadow_signals]):
        try:
            signals[name] = load_signal(policy, path, name)
        except (SignalError, ValueError) as exc:
            raise ServiceError(422, f"policy {path}: signal {name!r} is not ready: {exc}") from exc
    _warn_if_miscalibrated(path)
    inference = make_inference(settings, path, policy, signals)  # here, or a Ray actor (server.inference)
    controller = Controller(policy, signals, ctl.signal, spec.action_space, ctl.config(), inference, settings.seed)
    return PolicySlot(version, path, task, policy, float(signals["denoising"].threshold), controller, lineage)


def _warn_if_miscalibrated(path: Path) -> None:
    """Logs ``hitl calibrate``'s flag: its rollouts had far more steps above the threshold than the
    validation set, so this policy's robots would ask for help far more often than the quantile says."""
    try:
        check = (load_calibration(path) or {}).get("rollout_check") or {}
    except (OSError, ValueError, AttributeError):  # unreadable: the threshold's own loading reports it
        return
    if isinstance(check, dict) and check.get("flagged"):
        log.warning(
            "policy %s: calibration problem: %.0f%% of the steps of its %s calibration rollouts were above "
            "the threshold (flagged above %.0f%%); expect its robots to ask for help often",
            path,
            100 * check.get("share_above", 0.0),
            check.get("task", "?"),
            100 * check.get("flag_share", 0.0),
        )

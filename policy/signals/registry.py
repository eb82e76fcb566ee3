"""The signal registry (``make_signal``) and signal folders next to the policy.

``<policy>/signals/<name>/config.json`` holds the signal's config, its calibration and how it was
made; signals with auxiliary networks add ``model.safetensors``. Nothing is pickled.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

from safetensors.torch import load_file, save_file

from policy.checkpoint import CALIBRATION, load_calibration
from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import AssistanceSignal, SignalConfig, SignalError
from policy.signals.choice import ChoiceSignal
from policy.signals.choice_stall import ChoiceStallSignal
from policy.signals.critics import HulaSignal, ThriftySignal
from policy.signals.reference import FullTeleopSignal, RandomSignal
from policy.signals.sampling import DenoisingSignal, DiffDaggerSignal, OutputVarianceSignal, StacSignal
from policy.signals.spread import SpreadSignal
from policy.signals.stall import StallSignal

# every signal the fleet can be configured with (``signal = <name>``), each in one line
SIGNALS: dict[str, type[AssistanceSignal]] = {
    # the paper's metric: Gaussian mixtures fit to the denoising vectors in a ball around the pose (U = D + α·Var_g)
    "denoising": DenoisingSignal,
    # baseline: the variance of sampled action chunks' positions
    "output-variance": OutputVarianceSignal,
    # baseline (Diff-DAgger): the diffusion loss of the policy's own action
    "diff-dagger": DiffDaggerSignal,
    # baseline (ThriftyDAgger): ensemble novelty and a learned Q-risk, with its switch-back rule
    "thrifty": ThriftySignal,
    # baseline (STAC): the MMD between consecutive steps' sampled chunks on their overlap, summed over the episode
    "stac": StacSignal,
    # baseline (HULA, offline): the variance of an ensemble CQL critic's value estimate
    "hula-offline": HulaSignal,
    # the field read at a noise level k > 0 around the policy's next action, plus observation novelty
    "spread": SpreadSignal,
    # the policy stops making progress: its next action barely moves the end effector, gripper open
    "stall": StallSignal,
    # the policy's own sampled targets lie on both sides of the gripper: a choice of which way to go
    "choice": ChoiceSignal,
    # the fleet's default: ``choice`` on a scene the policy knows, ``stall`` on a new one
    "choice-stall": ChoiceStallSignal,
    # reference: the operator drives every step
    "full-teleop": FullTeleopSignal,
    # reference: asks at random steps at a set rate (to match another signal's rate against)
    "random": RandomSignal,
}

FORMAT = "hitl-assistance-signal/1"
SIGNAL_DIR = "signals"
CONFIG = "config.json"
WEIGHTS = "model.safetensors"


def signal_class(name: str) -> type[AssistanceSignal]:
    if name not in SIGNALS:
        raise KeyError(f"unknown signal {name!r}; registered signals: {', '.join(SIGNALS)}")
    return SIGNALS[name]


def config_from_dict(name: str, values: dict) -> SignalConfig:
    cls = signal_class(name).Config
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise SignalError(f"unknown {name} config keys {unknown}; known: {sorted(known)}")
    return cls(**values)


def make_signal(name: str, policy: DiffusionPolicy, config: SignalConfig | dict | None = None) -> AssistanceSignal:
    cls = signal_class(name)
    if isinstance(config, dict):
        config = config_from_dict(name, config)
    return cls(policy, config)


def signal_dir(policy_dir: str | Path, name: str) -> Path:
    return Path(policy_dir) / SIGNAL_DIR / name


def save_signal(signal: AssistanceSignal, policy_dir: str | Path, info: dict | None = None) -> Path:
    folder = signal_dir(policy_dir, signal.name)
    folder.mkdir(parents=True, exist_ok=True)
    if signal.has_models:
        state = {k: v.detach().contiguous().cpu() for k, v in signal.model_state().items()}
        save_file(state, str(folder / WEIGHTS), metadata={"format": FORMAT})
    doc = {
        "format": FORMAT,
        "signal": signal.name,
        "config": signal.config.to_dict(),
        "calibration": signal.calibration,
        **(info or {}),
    }
    (folder / CONFIG).write_text(json.dumps(doc, indent=2) + "\n")
    return folder


def load_signal(policy: DiffusionPolicy, policy_dir: str | Path, name: str) -> AssistanceSignal:
    """The calibrated signal saved by ``hitl train-signal`` (SignalError naming the missing file).

    Without a signal folder, ``full-teleop`` and ``random`` (nothing to learn) come with their
    defaults, and ``denoising`` takes its threshold from ``hitl calibrate``'s calibration.json.
    """
    folder = signal_dir(policy_dir, name)
    path = folder / CONFIG
    if not path.is_file() and name in ("full-teleop", "random"):
        return make_signal(name, policy)
    calibration = load_calibration(policy_dir) if not path.is_file() and name == "denoising" else None
    if calibration is not None:  # served with the settings it was calibrated with
        try:
            signal = make_signal(name, policy, dict(calibration.get("uncertainty") or {}))
        except (TypeError, ValueError) as exc:
            raise SignalError(f"{Path(policy_dir) / CALIBRATION}: bad uncertainty settings: {exc}") from exc
        signal.calibration = {"threshold": float(calibration["threshold"]), "source": CALIBRATION}
        return signal
    if not path.is_file():
        make_signal(name, policy)  # a signal that cannot work with this policy says why (SignalError)
        also = f" (or `hitl calibrate --policy {policy_dir}`)" if name == "denoising" else ""
        raise SignalError(f"{path} not found: run `hitl train-signal --policy {policy_dir} --signal {name}`{also}")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SignalError(f"{path} is not valid JSON: {exc}") from exc
    if doc.get("format") != FORMAT or doc.get("signal") != name:
        raise SignalError(f"{path}: expected format {FORMAT!r} for signal {name!r}")
    try:
        signal = make_signal(name, policy, doc.get("config", {}))
    except (TypeError, ValueError) as exc:
        raise SignalError(f"{path}: bad config: {exc}") from exc
    if signal.has_models:
        weights = folder / WEIGHTS
        if not weights.is_file():
            raise SignalError(f"{weights} not found")
        try:
            signal.load_model_state(load_file(str(weights)))
        except Exception as exc:  # safetensors and load_state_dict raise their own types
            raise SignalError(f"{weights}: cannot load: {exc}") from exc
    signal.calibration = doc.get("calibration")
    return signal

"""Policy checkpoints: ``model.safetensors`` (weights and normalizer buffers) + ``config.json``.

``config.json`` holds the policy config, the task, the dataset statistics and
the command that produced the checkpoint. ``calibration.json`` (written by
``hitl calibrate``) holds the uncertainty threshold. Nothing is pickled.
"""

from __future__ import annotations

import json
from pathlib import Path

from safetensors.torch import load_file, save_file

from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy

FORMAT = "hitl-diffusion-policy/1"
WEIGHTS = "model.safetensors"
CONFIG = "config.json"
CALIBRATION = "calibration.json"


class CheckpointError(ValueError):
    """A policy folder is missing, incomplete or inconsistent; the message says which file."""


def save_policy(policy: DiffusionPolicy, folder: str | Path, info: dict | None = None) -> Path:
    """Writes the policy to ``folder``; ``info`` (task, dataset, training, command) goes into config.json."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous().cpu() for k, v in policy.state_dict().items()}
    save_file(state, str(folder / WEIGHTS), metadata={"format": FORMAT})
    doc = {
        "format": FORMAT,
        "policy": policy.config.to_dict(),
        "normalization": {
            "obs": policy.obs_normalizer.stats(),
            "action": policy.action_normalizer.stats(),
            **({"frame_action": policy.frame_action_normalizer.stats()} if policy.frame is not None else {}),
        },
        **(info or {}),
    }
    (folder / CONFIG).write_text(json.dumps(doc, indent=2) + "\n")
    return folder


def read_info(folder: str | Path) -> dict:
    path = Path(folder) / CONFIG
    if not path.is_file():
        raise CheckpointError(f"{path} not found: is {folder} a policy folder written by `hitl train`?")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path} is not valid JSON: {exc}") from exc
    if doc.get("format") != FORMAT:
        raise CheckpointError(f"{path}: unsupported format {doc.get('format')!r}, expected {FORMAT!r}")
    return doc


def load_policy(folder: str | Path) -> tuple[DiffusionPolicy, dict]:
    """(policy in eval mode, config.json contents)."""
    folder = Path(folder)
    doc = read_info(folder)
    try:
        config = DiffusionPolicyConfig.from_dict(doc["policy"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{folder / CONFIG}: bad policy config: {exc}") from exc
    weights = folder / WEIGHTS
    if not weights.is_file():
        raise CheckpointError(f"{weights} not found")
    policy = DiffusionPolicy(config)
    try:
        state = load_file(str(weights))
        policy.load_state_dict(state, strict=True)
    except Exception as exc:  # safetensors raises its own error types for corrupt files
        raise CheckpointError(f"{weights}: cannot load weights: {exc}") from exc
    policy.eval()
    return policy, doc


def save_calibration(folder: str | Path, calibration: dict) -> Path:
    path = Path(folder) / CALIBRATION
    path.write_text(json.dumps(calibration, indent=2) + "\n")
    return path


def load_calibration(folder: str | Path) -> dict | None:
    path = Path(folder) / CALIBRATION
    if not path.is_file():
        return None
    return json.loads(path.read_text())

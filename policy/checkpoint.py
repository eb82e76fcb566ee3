"""Policy checkpoints: ``model.safetensors`` (weights and normalizer buffers) + ``config.json``.

``config.json`` holds the policy config, the task, the observation layout it was trained on
(``obs_labels``: the task's ``ObsSpec.labels``; older checkpoints have none), the dataset statistics and
the command that produced the checkpoint. ``calibration.json`` (written by
``hitl calibrate``) holds the uncertainty threshold. Nothing is pickled.

``check_fits`` says whether a checkpoint can run a task, and if not, everything that differs (the
observation layout, the cameras a policy sees against those the task declares, sizes, horizons): every
place that loads a policy to run a task calls it. A policy that sees cameras records them in its policy
config (``cameras``: name, rendered size, crop).
"""

from __future__ import annotations

import json
from pathlib import Path

from safetensors.torch import load_file, save_file

from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from storage import keys
from storage.obs_layout import describe, difference, recorded

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


def layout_info(obs_spec) -> dict:
    """The config.json entry recording the observation layout a policy is trained on (``save_policy``'s
    ``info``): ``{"obs_labels": [...]}`` from the task's ``ObsSpec``."""
    return {keys.OBS_LABELS: obs_spec.labels()}


def check_fits(info: dict, task: str, policy: str | Path = "the policy") -> None:
    """Raises CheckpointError naming every way the checkpoint whose config.json is ``info`` (``read_info``,
    ``load_policy``) cannot run ``task``: its observation channels against the task's (missing, extra or
    reordered, by name; by their number for a checkpoint that records no layout), its action size
    against ``sim.spaces.ACTION_DIM``, and its chunking (``obs_horizon``, ``action_horizon``) against
    the task's horizon. ``policy`` names it in the message. KeyError for a task that is not registered."""
    from sim.registry import make_task  # the simulated tasks only when a task is named
    from sim.spaces import ACTION_DIM

    make_task(task)  # KeyError for a task that is not registered
    try:
        config = DiffusionPolicyConfig.from_dict(info["policy"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"policy {policy}: bad policy config in {CONFIG}: {exc}") from exc
    spec = make_task(task, images=bool(config.cameras))  # names and specs only: the simulator is not built
    problems = []
    declared = {c.name: c for c in spec.cameras}
    for cam in config.cameras:
        have = declared.get(cam.name)
        if have is None:
            problems.append(
                f"it sees camera {cam.name!r}, which task {task} lacks (it has {', '.join(declared) or 'none'})"
            )
        elif have.size != cam.size:
            problems.append(f"it sees {cam.name!r} at {cam.size} pixels, task {task} renders {have.size}")
    want, labels = spec.obs_spec.labels(), recorded(info)
    if labels is not None and len(labels) != config.obs_dim:
        problems.append(f"its {CONFIG} records {len(labels)} observation channels for {config.obs_dim}-dim inputs")
    elif labels is not None and (diff := difference(labels, want)):
        problems.append(
            f"it was trained on observations {describe(labels)}, task {task} gives {describe(want)}: " + "; ".join(diff)
        )
    elif labels is None and config.obs_dim != len(want):
        problems.append(
            f"it takes {config.obs_dim}-dim observations (its {CONFIG} records no layout), task {task} gives "
            f"{len(want)}: {describe(want)}"
        )
    if config.action_dim != ACTION_DIM:
        problems.append(f"it predicts {config.action_dim}-dim actions, the tasks take {ACTION_DIM}")
    for name, steps in (("action_horizon", config.action_horizon), ("obs_horizon", config.obs_horizon)):
        if steps > spec.horizon:
            problems.append(f"its {name} of {steps} steps is longer than task {task}'s horizon of {spec.horizon}")
    if problems:
        raise CheckpointError(f"policy {policy} cannot run task {task}: " + "; ".join(problems))


def save_calibration(folder: str | Path, calibration: dict) -> Path:
    path = Path(folder) / CALIBRATION
    path.write_text(json.dumps(calibration, indent=2) + "\n")
    return path


def load_calibration(folder: str | Path) -> dict | None:
    path = Path(folder) / CALIBRATION
    if not path.is_file():
        return None
    return json.loads(path.read_text())

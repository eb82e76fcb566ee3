"""A LeRobotDataset (v3.0 layout) as demonstrations: MCAP episodes as ``hitl demos`` writes them.

The dataset's ``observation.state`` must be the task's observation (same size, and the same channel
names in the same order when the dataset names them) and its ``action`` our absolute end-effector action
(same size and names).
``observation.ee_pose`` (position + quaternion xyzw) is used when present, else the caller's
``pose_from_state`` computes it from the state (``hitl import``: from its ``eef_pos`` and
``eef_rot6d``). ``next.success``, ``action_source`` and ``observation.gripper`` are used when present.
An incompatible dataset is refused before anything is written, with every mismatched feature named, and
where the dataset names its channels, the channels it lacks or has beyond the task's.

For a policy that sees cameras (``cameras``: the task's), each camera's frames come from the image
feature ``observation.images.<camera>`` (LeRobot's ``image`` dtype: PNG or JPEG bytes in the parquet) of
the camera's size; a video feature, a missing camera or another size is refused by name, an image the
dataset holds for a camera the task does not declare is left out. Frames that cannot be decoded are
refused before any episode is written.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from tqdm import tqdm

from storage import keys
from storage.episodes import EpisodeWriter
from storage.images import ImageDecodeError, decode_png_bytes
from storage.lerobot.layout import (
    ACTION,
    CODEBASE_VERSION,
    EE_POSE,
    GRIPPER,
    INFO_PATH,
    SOURCE,
    STATE,
    SUCCESS,
)
from storage.obs_layout import describe, difference


class LeRobotImportError(Exception):
    """The folder is not a LeRobotDataset this project can use; the message says why."""


@dataclass
class ImportReport:
    out: Path
    episodes: int
    frames: int
    successes: int

    def as_dict(self) -> dict:
        return {
            "out": str(self.out),
            "episodes": int(self.episodes),
            "frames": int(self.frames),
            "successes": int(self.successes),
        }


def read_info(root: Path) -> dict:
    path = root / INFO_PATH
    if not path.is_file():
        raise LeRobotImportError(f"{root}: no {INFO_PATH}: not a LeRobotDataset")
    try:
        info = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LeRobotImportError(f"{path}: unreadable ({exc})") from exc
    version = str(info.get("codebase_version", ""))
    if version.split(".")[0] != CODEBASE_VERSION.split(".")[0]:
        raise LeRobotImportError(
            f"{root}: codebase_version {version or 'missing'}; this importer reads the {CODEBASE_VERSION} layout "
            "(LeRobot converts older datasets with lerobot.datasets.v30.convert_dataset_v21_to_v30)"
        )
    if not isinstance(info.get("features"), dict) or not isinstance(info.get("fps"), int | float):
        raise LeRobotImportError(f"{path}: no features or fps")
    return info


def _shape(feature: dict) -> list[int]:
    return [int(n) for n in feature.get("shape", [])]


def _names(feature: dict) -> list[str] | None:
    names = feature.get("names")
    if isinstance(names, dict) and len(names) == 1:  # LeRobot's {"motors": [...]} form
        names = next(iter(names.values()))
    return [str(n) for n in names] if isinstance(names, list) else None


def image_features(info: dict) -> list[str]:
    """The dataset's camera features (``observation.images.*``, image or video), by name."""
    return [k for k, f in info["features"].items() if isinstance(f, dict) and f.get("dtype") in ("image", "video")]


def check_compatible(
    info: dict,
    obs_labels: list[str],
    action_labels: list[str],
    can_compute_pose: bool = False,
    cameras: list[dict] | tuple[dict, ...] = (),
) -> list[str]:
    """Every way the dataset's state and action layout differs from the task's (empty: compatible): a
    feature's size, and where the dataset names its channels, those it lacks, those the task does not
    have and a different order, by name; for each camera in ``cameras`` (name, size), its image feature."""
    feats, problems = info["features"], []
    for cam in cameras:
        name, size = keys.image_key(cam["name"]), int(cam["size"])
        f = feats.get(name)
        if f is None:
            have = ", ".join(image_features(info)) or "none"
            problems.append(f"{name}: missing (the policy sees {cam['name']!r}; the dataset's cameras: {have})")
        elif f.get("dtype") == "video":
            problems.append(f"{name}: a video feature; this importer reads image features (LeRobot's use_videos=False)")
        elif f.get("dtype") != "image":
            problems.append(f"{name}: dtype {f.get('dtype')!r}, expected 'image'")
        elif _shape(f)[:2] != [size, size] or _shape(f)[2:] not in ([3], []):
            problems.append(f"{name}: shape {_shape(f)}, the task renders {cam['name']!r} at [{size}, {size}, 3]")
    for name, labels in ((STATE, obs_labels), (ACTION, action_labels)):
        f = feats.get(name)
        if f is None:
            problems.append(f"{name}: missing (the dataset has {', '.join(sorted(feats)) or 'no features'})")
            continue
        wrong, names = [], _names(f)
        if _shape(f) != [len(labels)]:
            wrong.append(f"shape {_shape(f)}, the task's is [{len(labels)}]")
        if names is not None:  # what differs, by channel name (storage.obs_layout)
            wrong += difference(labels, names)
        elif wrong:
            wrong.append(f"its channels are not named; the task's are {describe(labels)}")
        if wrong:
            problems.append(f"{name}: " + "; ".join(wrong))
    if EE_POSE in feats and _shape(feats[EE_POSE]) != [7]:
        problems.append(f"{EE_POSE}: shape {_shape(feats[EE_POSE])}, expected [7] (position + quaternion xyzw)")
    if EE_POSE not in feats and not can_compute_pose:
        problems.append(f"{EE_POSE}: missing, and the task's state does not give the end-effector pose")
    return problems


def _column(table, name: str) -> np.ndarray:
    return np.array(table.column(name).to_pylist())


def import_dataset(
    root: str | Path,
    out: str | Path,
    task: str,
    obs_labels: list[str],
    action_labels: list[str],
    pose_from_state: Callable[[np.ndarray], np.ndarray] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    cameras: list[dict] | tuple[dict, ...] = (),
) -> ImportReport:
    """Writes every episode of the dataset at ``root`` as an MCAP demonstration in ``out``.
    pose_from_state: (T, obs_dim) states -> (T, 7) end-effector poses, for a dataset without
    ``observation.ee_pose``; cameras: the task's (``CameraSpec.to_json``), for a policy that sees them."""
    root, out = Path(root), Path(out)
    info = read_info(root)
    if problems := check_compatible(info, obs_labels, action_labels, pose_from_state is not None, cameras):
        raise LeRobotImportError(f"{root} does not fit task {task}:\n  " + "\n  ".join(problems))
    files = sorted((root / "data").glob("chunk-*/file-*.parquet"))
    if not files:
        raise LeRobotImportError(f"{root}: no data/chunk-*/file-*.parquet files")
    if out.is_dir() and any(out.glob(keys.EPISODE_GLOB)) and not overwrite:
        raise LeRobotImportError(f"{out} already holds episodes (pass overwrite to add to it)")
    feats = info["features"]
    wanted = [
        c for c in (STATE, ACTION, EE_POSE, GRIPPER, SUCCESS, SOURCE, "episode_index", "frame_index") if c in feats
    ]
    wanted += [keys.image_key(c["name"]) for c in cameras]
    try:
        tables = [pq.read_table(f, columns=wanted) for f in files]
    except Exception as exc:  # noqa: BLE001 - pyarrow raises several types for a broken file
        raise LeRobotImportError(f"{root}: unreadable data file ({type(exc).__name__}: {exc})") from exc
    columns = {c: np.concatenate([_column(t, c) for t in tables]) for c in wanted}
    for cam in cameras:  # decoded before any episode is written: a broken frame refuses the dataset
        name, size = keys.image_key(cam["name"]), (int(cam["size"]),) * 2
        try:
            columns[name] = np.stack(
                [decode_png_bytes((cell or {}).get("bytes") or b"", size) for cell in columns[name]]
            )
        except ImageDecodeError as exc:
            raise LeRobotImportError(f"{root}: {name}: {exc}") from exc
    order = np.lexsort((columns["frame_index"], columns["episode_index"]))
    columns = {c: v[order] for c, v in columns.items()}
    episode = columns["episode_index"].astype(np.int64)
    finite = np.isfinite(columns[STATE]).all(axis=1) & np.isfinite(columns[ACTION]).all(axis=1)
    if not finite.all():  # before any file is written
        bad = sorted({int(i) for i in episode[~finite]})
        raise LeRobotImportError(f"{root}: episode(s) {bad[:10]} have non-finite state or action values")
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    ends = np.r_[starts[1:], len(episode)]
    source_codes = _names(feats[SOURCE]) if SOURCE in feats else None
    frames = successes = 0
    bar = tqdm(list(zip(starts, ends, strict=True)), desc="import lerobot", unit="ep", disable=not progress)
    for s, e in bar:
        idx = int(episode[s])
        state = columns[STATE][s:e].astype(np.float64)
        action = columns[ACTION][s:e].astype(np.float64)
        pose = columns[EE_POSE][s:e].astype(np.float64) if EE_POSE in columns else pose_from_state(state)
        gripper = columns[GRIPPER][s:e].reshape(-1) if GRIPPER in columns else np.zeros(e - s)
        success = columns[SUCCESS][s:e].astype(bool).reshape(-1) if SUCCESS in columns else np.zeros(e - s, bool)
        sources = [keys.SOURCE_EXPERT] * (e - s)
        if SOURCE in columns and source_codes is not None:
            sources = [
                source_codes[int(c)]
                if 0 <= int(c) < len(source_codes) and source_codes[int(c)] in keys.SOURCES
                else keys.SOURCE_EXPERT
                for c in columns[SOURCE][s:e].reshape(-1)
            ]
        meta = {
            "task": task,
            "seed": idx,
            "expert": "lerobot-import",
            "obs_labels": obs_labels,
            "action_labels": list(action_labels),
            "source": "lerobot",
            "lerobot": {"dataset": root.name, "episode_index": idx, "fps": info["fps"]},
        }
        path = out / f"{task}_lerobot{idx:06d}.mcap"
        with EpisodeWriter(path, meta, cameras=list(cameras)) as writer:
            for t in range(e - s):
                images = {c["name"]: columns[keys.image_key(c["name"])][s + t] for c in cameras}
                writer.write_step(
                    t,
                    state[t],
                    action[t],
                    pose[t, :3],
                    pose[t, 3:],
                    float(gripper[t]),
                    bool(success[t]),
                    sources[t],
                    images=images,
                )
            won = bool(success.any())
            writer.finish(won, e - s, "success" if won else "horizon")
        frames += e - s
        successes += won
    return ImportReport(out, len(starts), frames, successes)

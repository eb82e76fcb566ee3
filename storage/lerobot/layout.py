"""The LeRobotDataset v3.0 layout, written with pyarrow and pandas.

LeRobot's own package cannot be installed beside our torch: every release that reads v3.0
(``lerobot>=0.4``) requires ``torch<2.11``, and the releases that fit (0.3.x) read only v2.1. So the
layout is written here, as LeRobot documents and writes it:

- ``meta/info.json``: ``codebase_version`` "v3.0", ``fps``, the feature schema (dtype, shape, names),
  totals, ``chunks_size``, ``data_files_size_in_mb``, ``data_path`` and ``splits``;
- ``meta/stats.json``: per feature min, max, mean, std, count and the 1/10/50/90/99 % quantiles;
- ``meta/tasks.parquet``: one row per task string (the index) with its ``task_index``;
- ``meta/episodes/chunk-XXX/file-YYY.parquet``: per episode its index, tasks, length, where its frames
  lie (``data/chunk_index``, ``data/file_index``, ``dataset_from_index``, ``dataset_to_index``), its
  stats (``stats/<feature>/<stat>``) and our own columns (``hitl/...``: kind, source file, outcome,
  seed, robot, fleet episode, policy, the takeovers with their labels as JSON);
- ``data/chunk-XXX/file-YYY.parquet``: the frames, one column per feature; vectors as fixed-size
  lists, as ``datasets`` writes them. What a policy that sees saw is an ``image`` feature per camera,
  ``observation.images.<camera>`` (shape [height, width, 3], names [height, width, channels]), its PNG
  bytes embedded in the parquet as ``{"bytes", "path"}`` structs, as LeRobot stores image features
  (``use_videos=False``): the recorded bytes themselves, lossless, no video codec to decode; its stats
  are per channel in [0, 1], shaped [3, 1, 1], as LeRobot's. An episode never spans two files; a file
  holds whole episodes up to about ``data_files_size_in_mb``, a chunk ``chunks_size`` files.

Episode and frame indices are contiguous and increasing: ``index`` runs over the whole dataset,
``frame_index`` within the episode, ``timestamp`` is ``frame_index / fps``.
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from storage import keys
from storage.lerobot.attempts import COMMAND_DIM, LABEL_CODES, Attempt

CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
DEFAULT_FEATURES = {  # every LeRobot dataset has these
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
POSE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw"]
IMAGE_TYPE = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
COMMAND_NAMES = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]

# feature names, shared with the importer
STATE, EE_POSE, GRIPPER, ACTION = "observation.state", "observation.ee_pose", "observation.gripper", "action"
DONE, SUCCESS, INTERVENTION, SOURCE = "next.done", "next.success", "intervention", "action_source"
COMMAND, SCORED, SCORE, THRESHOLD = "operator.command", "asking.scored", "asking.score", "asking.threshold"
POLICY_VERSION, TAKEOVER, LABEL, DISCARDED = "policy_version", "takeover.id", "takeover.label", "takeover.discarded"


class ExportError(Exception):
    """The attempts cannot be written as one dataset (nothing to export, mixed dimensions, ...)."""


def image_feature(camera: dict) -> tuple[str, dict]:
    """LeRobot's image feature for one camera (``CameraSpec.to_json``: name, size)."""
    size = int(camera["size"])
    return keys.image_key(camera["name"]), {
        "dtype": "image",
        "shape": [size, size, 3],
        "names": ["height", "width", "channels"],
    }


def features(
    obs_labels: list[str], obs_dim: int, action_labels: list[str], action_dim: int, cameras: list[dict] = ()
) -> dict[str, dict]:
    """The dataset's features (LeRobot's schema: dtype, shape, names), ours then LeRobot's defaults."""
    names = obs_labels if len(obs_labels) == obs_dim else None
    action_names = list(action_labels) if len(action_labels) == action_dim else None
    ours = {
        STATE: {"dtype": "float32", "shape": [obs_dim], "names": names},
        EE_POSE: {"dtype": "float32", "shape": [7], "names": POSE_NAMES},
        GRIPPER: {"dtype": "float32", "shape": [1], "names": ["finger_gap_m"]},
        ACTION: {"dtype": "float32", "shape": [action_dim], "names": action_names},
        DONE: {"dtype": "bool", "shape": [1], "names": None},
        SUCCESS: {"dtype": "bool", "shape": [1], "names": None},
        INTERVENTION: {"dtype": "bool", "shape": [1], "names": None},
        SOURCE: {"dtype": "int64", "shape": [1], "names": {"codes": list(keys.SOURCES)}},
        COMMAND: {"dtype": "float32", "shape": [COMMAND_DIM], "names": COMMAND_NAMES},
        SCORED: {"dtype": "bool", "shape": [1], "names": None},
        SCORE: {"dtype": "float32", "shape": [1], "names": None},
        THRESHOLD: {"dtype": "float32", "shape": [1], "names": None},
        POLICY_VERSION: {"dtype": "int64", "shape": [1], "names": None},
        TAKEOVER: {"dtype": "int64", "shape": [1], "names": None},
        LABEL: {"dtype": "int64", "shape": [1], "names": {"codes": {k or "none": v for k, v in LABEL_CODES.items()}}},
        DISCARDED: {"dtype": "bool", "shape": [1], "names": None},
    }
    return ours | dict(image_feature(c) for c in cameras) | DEFAULT_FEATURES


def _columns(a: Attempt, episode_index: int, start: int, task_index: int, fps: int) -> dict[str, np.ndarray]:
    n = len(a)
    frame = np.arange(n, dtype=np.int64)
    label, discarded = a.label_codes()
    return {
        STATE: a.obs.astype(np.float32),
        EE_POSE: a.ee_pose.astype(np.float32),
        GRIPPER: a.gripper.astype(np.float32),
        ACTION: a.action.astype(np.float32),
        DONE: frame == n - 1,  # the attempt ends after its last frame
        SUCCESS: a.success.astype(bool),
        INTERVENTION: a.intervention,
        SOURCE: a.action_source.astype(np.int64),
        COMMAND: a.command.astype(np.float32),
        SCORED: a.scored.astype(bool),
        SCORE: a.score.astype(np.float32),
        THRESHOLD: a.threshold.astype(np.float32),
        POLICY_VERSION: a.policy_version.astype(np.int64),
        TAKEOVER: a.takeover.astype(np.int64),
        LABEL: label,
        DISCARDED: discarded,
        "timestamp": (frame / fps).astype(np.float32),
        "frame_index": frame,
        "episode_index": np.full(n, episode_index, np.int64),
        "index": start + frame,
        "task_index": np.full(n, task_index, np.int64),
    } | {keys.image_key(name): frames for name, frames in a.images.items()}


def _arrow(columns: dict[str, np.ndarray], feats: dict[str, dict]) -> pa.Table:
    arrays = {}
    for name, values in columns.items():
        if feats[name]["dtype"] == "image":  # LeRobot's (datasets') Image: {bytes, path} structs
            arrays[name] = pa.array([{"bytes": b, "path": None} for b in values], type=IMAGE_TYPE)
            continue
        dtype = pa.from_numpy_dtype(np.dtype(feats[name]["dtype"]))
        if feats[name]["shape"] == [1]:
            arrays[name] = pa.array(values.reshape(-1), type=dtype)
        else:
            width = feats[name]["shape"][0]
            flat = pa.array(np.ascontiguousarray(values).reshape(-1), type=dtype)
            arrays[name] = pa.FixedSizeListArray.from_arrays(flat, width)
    return pa.table(arrays)


def feature_stats(values: np.ndarray) -> dict[str, list]:
    """LeRobot's per-feature stats of (N, ...) values: per dimension min, max, mean, std, the quantiles,
    and the count."""
    x = np.asarray(values, np.float64).reshape(len(values), -1)
    out = {
        "min": x.min(axis=0),
        "max": x.max(axis=0),
        "mean": x.mean(axis=0),
        "std": x.std(axis=0),
    }
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(x, q, axis=0)
    return {k: v.tolist() for k, v in out.items()} | {"count": [len(x)]}


def image_stats(pngs: list[bytes], most: int = 100) -> dict[str, list]:
    """LeRobot's stats of an image feature: per channel in [0, 1], each shaped [3, 1, 1], over up to
    ``most`` of the frames evenly spaced (LeRobot samples frames too)."""
    from storage.images import decode_png_bytes

    picked = pngs[:: max(1, -(-len(pngs) // most))]
    pixels = np.concatenate([decode_png_bytes(b).reshape(-1, 3) for b in picked]) / 255.0
    stats = feature_stats(pixels)
    return {k: (np.asarray(v).reshape(3, 1, 1).tolist() if k != "count" else [len(pngs)]) for k, v in stats.items()}


@dataclass
class ExportReport:
    root: Path
    episodes: int
    frames: int
    tasks: list[str]
    files: int
    kinds: dict[str, int]

    def as_dict(self) -> dict:
        return {
            "root": str(self.root),
            "codebase_version": CODEBASE_VERSION,
            "episodes": self.episodes,
            "frames": self.frames,
            "tasks": self.tasks,
            "data_files": self.files,
            "kinds": self.kinds,
        }


def write_dataset(
    attempts: list[Attempt],
    root: str | Path,
    fps: int,
    action_labels: list[str],
    task_texts: dict[str, str] | None = None,
    robot_type: str | None = None,
    chunks_size: int = 1000,
    data_files_size_in_mb: float = 100.0,
    overwrite: bool = False,
    progress: bool = True,
) -> ExportReport:
    """Writes ``attempts`` (in order: episode i is attempts[i]) as a LeRobotDataset at ``root``.

    action_labels: the names of the action's dimensions; task_texts: task name -> the task string
    LeRobot keeps (a language instruction; default the name).
    A non-empty ``root`` is refused unless ``overwrite``. The dataset is assembled beside ``root`` and
    moved into place at the end, so a failed export leaves no half-written dataset."""
    root = Path(root)
    attempts = [a for a in attempts if len(a)]
    if not attempts:
        raise ExportError("nothing to export: no frames in the selection")
    dims = {(a.obs.shape[1], a.action.shape[1]) for a in attempts}
    if len(dims) != 1:
        raise ExportError(f"the selection mixes observation/action sizes {sorted(dims)}: export one task at a time")
    cameras = attempts[0].cameras
    if other := [a.source for a in attempts if a.cameras != cameras]:
        raise ExportError(f"the selection mixes camera sets ({other[0]}, {attempts[0].source}): export one at a time")
    if short := [a.source for a in attempts if any(len(a.images.get(c["name"], [])) != len(a) for c in cameras)]:
        raise ExportError(f"{short[0]} lacks frames of some steps: it cannot be exported with its cameras")
    if root.exists() and any(root.iterdir()) and not overwrite:
        raise ExportError(f"{root} is not empty (pass overwrite to replace it)")
    obs_dim = attempts[0].obs.shape[1]
    labels = next((a.obs_labels for a in attempts if len(a.obs_labels) == obs_dim), [])
    feats = features(labels, obs_dim, action_labels, attempts[0].action.shape[1], cameras)
    texts = task_texts or {}
    task_strings = list(dict.fromkeys(texts.get(a.task, a.task) for a in attempts))
    row_bytes = sum(
        (8 if f["dtype"] == "int64" else 4) * int(np.prod(f["shape"])) for f in feats.values() if f["dtype"] != "image"
    )
    row_bytes += sum(len(a.images[c["name"]][0]) for c in cameras for a in attempts[:1])  # a frame's PNG
    frames_per_file = max(1, int(data_files_size_in_mb * 2**20 / row_bytes))

    tmp = root.with_name(root.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        episodes_rows, all_columns = [], {name: [] for name in feats}
        chunk, file, in_file, start, files = 0, 0, 0, 0, 0
        pending: list[pa.Table] = []

        def flush() -> None:
            nonlocal files
            if pending:
                path = tmp / DATA_PATH.format(chunk_index=chunk, file_index=file)
                path.parent.mkdir(parents=True, exist_ok=True)
                pq.write_table(pa.concat_tables(pending), path)
                pending.clear()
                files += 1

        bar = tqdm(attempts, desc="export lerobot", unit="ep", disable=not progress)
        for i, a in enumerate(bar):
            if in_file and in_file + len(a) > frames_per_file:
                flush()
                file, in_file = file + 1, 0
                if file >= chunks_size:
                    chunk, file = chunk + 1, 0
            task = texts.get(a.task, a.task)
            cols = _columns(a, i, start, task_strings.index(task), fps)
            pending.append(_arrow(cols, feats))
            for name, values in cols.items():
                all_columns[name].append(values)
            row = {
                "episode_index": i,
                "tasks": [task],
                "length": len(a),
                "data/chunk_index": chunk,
                "data/file_index": file,
                "dataset_from_index": start,
                "dataset_to_index": start + len(a),
                "meta/episodes/chunk_index": 0,
                "meta/episodes/file_index": 0,
                "hitl/task": a.task,
                "hitl/kind": a.kind,
                "hitl/source": a.source,
                "hitl/meta": json.dumps(a.meta, default=str),
                "hitl/takeovers": json.dumps({str(k): v.as_dict() for k, v in a.takeovers.items()}),
            }
            for name, values in cols.items():
                stats_of = image_stats if feats[name]["dtype"] == "image" else feature_stats
                for stat, v in stats_of(values).items():
                    row[f"stats/{name}/{stat}"] = v
            episodes_rows.append(row)
            start += len(a)
            in_file += len(a)
        flush()

        episodes_path = tmp / EPISODES_PATH.format(chunk_index=0, file_index=0)
        episodes_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(episodes_rows), episodes_path)
        pd.DataFrame({"task_index": range(len(task_strings))}, index=pd.Index(task_strings, name="task")).to_parquet(
            tmp / TASKS_PATH
        )
        stats = {
            name: image_stats([b for part in v for b in part])
            if feats[name]["dtype"] == "image"
            else feature_stats(np.concatenate(v))
            for name, v in all_columns.items()
        }
        (tmp / STATS_PATH).write_text(json.dumps(stats, indent=2))
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": robot_type,
            "total_episodes": len(attempts),
            "total_frames": start,
            "total_tasks": len(task_strings),
            "chunks_size": chunks_size,
            "data_files_size_in_mb": data_files_size_in_mb,
            "video_files_size_in_mb": 200,
            "fps": fps,
            "splits": {"train": f"0:{len(attempts)}"},
            "data_path": DATA_PATH,
            "video_path": None,
            "features": feats,
        }
        (tmp / INFO_PATH).write_text(json.dumps(info, indent=4))
        if root.exists():
            shutil.rmtree(root)
        tmp.rename(root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    kinds = dict(Counter(a.kind for a in attempts))
    return ExportReport(root, len(attempts), start, task_strings, files, kinds)

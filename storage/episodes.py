"""Episodes as MCAP files: one file per episode, JSON messages with JSON schemas.

Two families of channel:

- training data: ``/episode`` (metadata, first), ``/step`` (observation, action,
  end-effector pose, gripper, success, source; one per control step) and
  ``/outcome`` (last);
- 3D playback for Foxglove: ``/tf`` (``foxglove.FrameTransform``) and
  ``/poses/...`` (``foxglove.PoseInFrame``) for the end effector and objects;
- for a policy that sees cameras, ``/observation/images/<camera>``: what each of its cameras saw
  before each step's action (``foxglove.CompressedImage``, PNG: lossless, so a policy trained on the
  file sees what the robot saw; ``storage.images``), at the step's time. The cameras and their sizes
  are in the metadata (``keys.CAMERAS``).

Vectors are stored as JSON float64, which round-trips exactly. The writer
closes a chunk and flushes the file every ``flush_every`` steps, so a file cut
off by a crash keeps every message up to the last flush; ``read_episode(path,
recover=True)`` salvages them with the non-seeking reader.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError

from storage import keys
from storage.images import COMPRESSED_IMAGE_SCHEMA, ImageDecodeError, check_frame, decode_png, png_message
from storage.mcap_io import JsonMcapWriter, read_all, rebuild, salvage, stamp

_VEC = {"type": "array", "items": {"type": "number"}}
_VEC3 = {
    "type": "object",
    "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}},
}
_QUAT = {
    "type": "object",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
}
_TIME = {
    "type": "object",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
SCHEMAS: dict[str, dict] = {
    keys.SCHEMA_EPISODE: {
        "type": "object",
        "properties": {
            "task": {"type": "string"},
            "seed": {"type": "integer"},
            "expert": {"type": "string"},
            "object": {"type": "string"},
            "obs_labels": {"type": "array", "items": {"type": "string"}},
            "action_labels": {"type": "array", "items": {"type": "string"}},
        },
    },
    keys.SCHEMA_STEP: {
        "type": "object",
        "properties": {
            keys.STEP_T: {"type": "integer"},
            keys.STEP_OBSERVATION: _VEC,
            keys.STEP_ACTION: _VEC,
            keys.STEP_EE_POSE: {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}},
            keys.STEP_GRIPPER: {"type": "number", "description": "finger gap (m)"},
            keys.STEP_SUCCESS: {"type": "boolean"},
            keys.STEP_SOURCE: {"type": "string", "enum": list(keys.SOURCES)},
            keys.STEP_SCORE: {"type": "number"},
            keys.STEP_THRESHOLD: {"type": "number"},
            keys.STEP_PAPER_U: {"type": "number", "description": "the paper's denoising U"},
            keys.STEP_POLICY_VERSION: {"type": "integer"},
            keys.STEP_COMMAND: {
                "type": "object",
                "properties": {"delta_pos": _VEC, "delta_rot": _VEC, "gripper": {"type": ["number", "null"]}},
            },
            keys.STEP_TAKEOVER: {"type": "integer"},
        },
    },
    keys.SCHEMA_OUTCOME: {
        "type": "object",
        "properties": {"success": {"type": "boolean"}, "steps": {"type": "integer"}, "reason": {"type": "string"}},
    },
    # Foxglove well-known schemas (JSON encoding).
    keys.SCHEMA_COMPRESSED_IMAGE: COMPRESSED_IMAGE_SCHEMA,
    keys.SCHEMA_FRAME_TRANSFORM: {
        "title": "foxglove.FrameTransform",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"},
            "translation": _VEC3,
            "rotation": _QUAT,
        },
    },
    keys.SCHEMA_POSE_IN_FRAME: {
        "title": "foxglove.PoseInFrame",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}},
        },
    },
}

CONTROL_PERIOD_NS = 50_000_000  # 20 Hz


class EpisodeReadError(Exception):
    """An episode file could not be read; the message names the file and what to do."""

    def __init__(self, path: Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class TruncatedEpisodeError(EpisodeReadError):
    """The file has no summary/footer (cut off while recording)."""


@dataclass
class Episode:
    """A decoded episode. Arrays are float64, one row per control step."""

    path: Path
    meta: dict
    obs: np.ndarray  # (T, obs_dim)
    actions: np.ndarray  # (T, 10)
    ee_pose: np.ndarray  # (T, 7) position + quaternion xyzw
    gripper: np.ndarray  # (T,)
    success: np.ndarray  # (T,) bool
    sources: list[str]
    outcome: dict | None  # None when the file was recovered from a truncation
    extras: list[dict] = field(default_factory=list)  # per step: the ``keys.STEP_EXTRAS`` it carries
    # camera -> its frames' foxglove.CompressedImage messages, one per step in order (``frames`` decodes them)
    images: dict[str, list[dict]] = field(default_factory=dict)
    recovered: bool = False
    playback_messages: int = 0

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def cameras(self) -> list[dict]:
        """The policy cameras the episode recorded (``keys.CAMERAS``: name, size, crop), in order."""
        return list(self.meta.get(keys.CAMERAS) or [])

    def frames(self, camera: str) -> np.ndarray:
        """(T, size, size, 3) uint8: what ``camera`` saw at each step. EpisodeReadError when the episode
        lacks a frame of a step, or one is not a PNG of the recorded size."""
        spec = next((c for c in self.cameras if c.get("name") == camera), None)
        if spec is None:
            raise EpisodeReadError(
                self.path, f"no camera {camera!r}; it recorded {[c.get('name') for c in self.cameras]}"
            )
        messages = self.images.get(camera, [])
        if len(messages) != len(self):
            raise EpisodeReadError(self.path, f"camera {camera!r}: {len(messages)} frames for {len(self)} steps")
        size = (int(spec["size"]), int(spec["size"]))
        try:
            return np.stack([decode_png(m, size) for m in messages]) if messages else np.zeros((0, *size, 3), np.uint8)
        except ImageDecodeError as exc:
            raise EpisodeReadError(self.path, f"camera {camera!r}: {exc}") from exc


def _xyz(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(q) -> dict:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


class EpisodeWriter:
    """Writes one episode to ``path``; use as a context manager.

    Args:
        path: the ``.mcap`` file to create (parents are created).
        meta: episode metadata (task, seed, expert, object, ...), JSON-serialisable.
        object_names: the objects whose poses are streamed for playback.
        flush_every: close a chunk and flush the file every this many steps.
        cameras: the policy cameras whose frames every step carries (``CameraSpec.to_json`` dicts: name,
            size, crop); recorded in the metadata under ``keys.CAMERAS``.
    """

    def __init__(
        self,
        path: str | Path,
        meta: dict,
        object_names: list[str] | tuple[str, ...] = (),
        flush_every: int = 20,
        start_time_ns: int | None = None,
        cameras: list[dict] | tuple[dict, ...] = (),
    ) -> None:
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        self._sizes = {str(c["name"]): int(c["size"]) for c in cameras}
        if len(self._sizes) != len(cameras):
            raise ValueError(f"cameras named twice: {[c['name'] for c in cameras]}")
        self.path = Path(path)
        self._mcap = JsonMcapWriter(self.path, SCHEMAS, chunk_size=256 * 1024)
        self._flush_every = flush_every
        self._t0 = time.time_ns() if start_time_ns is None else int(start_time_ns)
        self._steps = 0
        channel = self._mcap.channel
        self._ch_episode = channel(keys.TOPIC_EPISODE, keys.SCHEMA_EPISODE)
        self._ch_step = channel(keys.TOPIC_STEP, keys.SCHEMA_STEP)
        self._ch_outcome = channel(keys.TOPIC_OUTCOME, keys.SCHEMA_OUTCOME)
        self._ch_tf = channel(keys.TOPIC_TF, keys.SCHEMA_FRAME_TRANSFORM)
        self._ch_ee = channel(keys.TOPIC_EE_POSE, keys.SCHEMA_POSE_IN_FRAME)
        self._ch_objects = {
            name: channel(keys.TOPIC_OBJECT_POSE.format(name=name), keys.SCHEMA_POSE_IN_FRAME) for name in object_names
        }
        self._ch_images = {
            name: channel(keys.TOPIC_POLICY_IMAGE.format(name=name), keys.SCHEMA_COMPRESSED_IMAGE)
            for name in self._sizes
        }
        self.meta = dict(meta) | ({keys.CAMERAS: [dict(c) for c in cameras]} if cameras else {})
        self._mcap.add_metadata("episode", self.meta)
        self._add(self._ch_episode, self._t0, self.meta)
        self._mcap.flush()

    def _add(self, channel: int, ns: int, payload: dict) -> None:
        self._mcap.add(channel, ns, payload)

    def write_step(
        self,
        t: int,
        obs: np.ndarray,
        action: np.ndarray,
        ee_pos: np.ndarray,
        ee_quat: np.ndarray,
        gripper: float,
        success: bool,
        source: str = keys.SOURCE_EXPERT,
        objects: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
        extras: dict | None = None,
        images: dict[str, np.ndarray] | None = None,
    ) -> None:
        """One control step: the observation before the action, and the action taken. ``extras``: the
        optional ``keys.STEP_EXTRAS`` the fleet knows (asking score and threshold, the paper's U, policy
        version, operator command, takeover id); other keys are refused. ``images``: camera -> (size,
        size, 3) uint8, what each declared camera saw before the action (every one, every step)."""
        images = images or {}
        if set(images) != set(self._sizes):
            raise ValueError(
                f"step {t}: frames of cameras {sorted(images)}, the episode declared {sorted(self._sizes)}"
            )
        for name, image in images.items():
            size = self._sizes[name]
            if check_frame(image, name).shape[:2] != (size, size):
                raise ValueError(f"step {t}: camera {name!r} frame is {np.shape(image)}, declared {size}x{size}")
        extras = {k: v for k, v in (extras or {}).items() if v is not None}
        if unknown := set(extras) - set(keys.STEP_EXTRAS):
            raise ValueError(f"unknown step fields {sorted(unknown)}; known: {keys.STEP_EXTRAS}")
        if source not in keys.SOURCES:
            raise ValueError(f"source must be one of {keys.SOURCES}, got {source!r}")
        obs = np.asarray(obs, dtype=np.float64)
        action = np.asarray(action, dtype=np.float64)
        if not (np.all(np.isfinite(obs)) and np.all(np.isfinite(action))):
            raise ValueError(f"step {t}: observation/action must be finite")
        ns = self._t0 + int(t) * CONTROL_PERIOD_NS
        pose = {"position": _xyz(ee_pos), "orientation": _quat(ee_quat)}
        self._add(
            self._ch_step,
            ns,
            {
                keys.STEP_T: int(t),
                keys.STEP_OBSERVATION: obs.tolist(),
                keys.STEP_ACTION: action.tolist(),
                keys.STEP_EE_POSE: pose,
                keys.STEP_GRIPPER: float(gripper),
                keys.STEP_SUCCESS: bool(success),
                keys.STEP_SOURCE: source,
            }
            | extras,
        )
        for name, image in images.items():
            self._add(self._ch_images[name], ns, png_message(image, name, ns))
        self._add_frame(ns, keys.EE_FRAME, ee_pos, ee_quat)
        self._add(self._ch_ee, ns, {"timestamp": stamp(ns), "frame_id": keys.WORLD_FRAME, "pose": pose})
        for name, (pos, quat) in (objects or {}).items():
            if name not in self._ch_objects:
                raise KeyError(f"object {name!r} was not declared when the episode was opened")
            self._add_frame(ns, name, pos, quat)
            self._add(
                self._ch_objects[name],
                ns,
                {
                    "timestamp": stamp(ns),
                    "frame_id": keys.WORLD_FRAME,
                    "pose": {"position": _xyz(pos), "orientation": _quat(quat)},
                },
            )
        self._steps += 1
        if self._steps % self._flush_every == 0:
            self.flush()

    def _add_frame(self, ns: int, child: str, pos, quat) -> None:
        self._add(
            self._ch_tf,
            ns,
            {
                "timestamp": stamp(ns),
                "parent_frame_id": keys.WORLD_FRAME,
                "child_frame_id": child,
                "translation": _xyz(pos),
                "rotation": _quat(quat),
            },
        )

    def flush(self) -> None:
        """Closes the current chunk and flushes it to disk."""
        self._mcap.flush()

    def finish(self, success: bool, steps: int, reason: str = "") -> None:
        ns = self._t0 + int(steps) * CONTROL_PERIOD_NS
        self._add(self._ch_outcome, ns, {"success": bool(success), "steps": int(steps), "reason": reason})
        self.close()

    def close(self) -> None:
        """Writes the summary and footer. An episode closed without ``finish`` has no outcome."""
        self._mcap.close()

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _decode(path: Path, messages) -> Episode:
    meta: dict | None = None
    outcome: dict | None = None
    steps: list[dict] = []
    frames: dict[str, list[tuple[int, dict]]] = {}
    t0: int | None = None
    playback = 0
    image_topic = keys.TOPIC_POLICY_IMAGE.format(name="")
    for _schema, channel, message in messages:
        if channel.topic.startswith(image_topic):
            try:
                frames.setdefault(channel.topic[len(image_topic) :], []).append(
                    (message.log_time, json.loads(message.data))
                )
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise EpisodeReadError(path, f"corrupt message on {channel.topic}: {exc}") from exc
            continue
        if channel.topic == keys.TOPIC_EPISODE:
            t0 = message.log_time
        if channel.topic in (keys.TOPIC_STEP, keys.TOPIC_EPISODE, keys.TOPIC_OUTCOME):
            try:
                payload = json.loads(message.data)
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise EpisodeReadError(path, f"corrupt message on {channel.topic}: {exc}") from exc
            if channel.topic == keys.TOPIC_STEP:
                steps.append(payload)
            elif channel.topic == keys.TOPIC_EPISODE:
                meta = payload
            else:
                outcome = payload
        else:
            playback += 1
    if meta is None:
        raise EpisodeReadError(path, f"no {keys.TOPIC_EPISODE} message: not a hitl episode, or cut off before it")
    steps.sort(key=lambda s: s[keys.STEP_T])
    try:
        obs = np.array([s[keys.STEP_OBSERVATION] for s in steps], dtype=np.float64)
        actions = np.array([s[keys.STEP_ACTION] for s in steps], dtype=np.float64)
        pose = keys.STEP_EE_POSE
        ee = np.array(
            [[*(s[pose]["position"][k] for k in "xyz"), *(s[pose]["orientation"][k] for k in "xyzw")] for s in steps],
            dtype=np.float64,
        )
        n = len(steps)
        obs = obs.reshape(n, -1) if n else np.zeros((0, 0))  # cut off before the first step was flushed
        actions = actions.reshape(n, -1) if n else np.zeros((0, 10))
        ee = ee.reshape(n, 7)
    except (KeyError, TypeError, ValueError) as exc:
        raise EpisodeReadError(path, f"malformed {keys.TOPIC_STEP} messages: {exc}") from exc
    return Episode(
        path=path,
        meta=meta,
        obs=obs,
        actions=actions,
        ee_pose=ee,
        gripper=np.array([s[keys.STEP_GRIPPER] for s in steps], dtype=np.float64),
        success=np.array([s[keys.STEP_SUCCESS] for s in steps], dtype=bool),
        sources=[s[keys.STEP_SOURCE] for s in steps],
        outcome=outcome,
        extras=[{k: s[k] for k in keys.STEP_EXTRAS if k in s} for s in steps],
        images=_frames_by_step(path, frames, t0, [s[keys.STEP_T] for s in steps]),
        playback_messages=playback,
    )


def _frames_by_step(path: Path, frames: dict[str, list[tuple[int, dict]]], t0: int | None, ts: list[int]):
    """camera -> its messages in step order, each matched to its step by time (a step at ``t`` is logged at
    the episode's start plus ``t`` control periods); frames of steps the file lacks (cut off) are dropped."""
    out: dict[str, list[dict]] = {}
    wanted = set(ts)
    for camera, messages in frames.items():
        by_t = {}
        for ns, m in messages:
            t = (ns - (t0 or 0)) // CONTROL_PERIOD_NS
            if t in by_t:
                raise EpisodeReadError(path, f"camera {camera!r}: two frames at step {t}")
            by_t[t] = m
        out[camera] = [by_t[t] for t in ts if t in by_t and t in wanted]
    return out


_TRUNCATED_HINT = (
    "the file has no intact summary/footer, so it was probably cut off while recording. "
    "read_episode(path, recover=True) (or `hitl inspect --recover FILE`) salvages every message up to "
    "the last flushed chunk with the non-seeking MCAP reader"
)


def recover_episode(path: str | Path, reason: str = "interrupted") -> int:
    """Rewrites an episode file left open by a crash as a complete, indexed MCAP that ends with an
    ``/outcome`` (success false, the steps it keeps, ``reason``); returns those steps. A file that
    already ends cleanly is left as it is. Raises EpisodeReadError when nothing is readable."""
    path = Path(path)
    episode = read_episode(path, recover=True)
    if not episode.recovered and episode.outcome is not None:
        return len(episode.actions)
    steps = len(episode.actions)
    rebuild(path, {keys.TOPIC_OUTCOME: {"success": False, "steps": steps, "reason": reason}})
    return steps


def read_episode(path: str | Path, recover: bool = False) -> Episode:
    """Reads one episode file.

    Args:
        recover: for a file cut off while recording, return everything up to the
            last flushed chunk (``Episode.recovered`` is True, ``outcome`` is None)
            instead of raising ``TruncatedEpisodeError``.
    """
    path = Path(path)
    if not path.is_file():
        raise EpisodeReadError(path, "no such file")
    try:
        return _decode(path, read_all(path))
    except EpisodeReadError:
        raise
    except Exception as exc:  # noqa: BLE001 - mcap raises several types for broken files
        seek_error = f"{type(exc).__name__}: {exc}"
    messages, stopped = salvage(path)
    if not messages:
        raise EpisodeReadError(path, f"not a readable MCAP episode ({seek_error}; {stopped})")
    if not recover:
        raise TruncatedEpisodeError(
            path, f"{_TRUNCATED_HINT} ({len(messages)} messages are recoverable; reader said: {seek_error})"
        )
    episode = _decode(path, messages)
    episode.recovered = True
    return episode


__all__ = [
    "Episode",
    "EpisodeReadError",
    "EpisodeWriter",
    "McapError",
    "TruncatedEpisodeError",
    "read_episode",
    "recover_episode",
]

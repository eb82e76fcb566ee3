"""Takeover segments: one MCAP file per operator takeover, the fine-tuning data of the product.

Once, first (``/takeover``, and the file's ``takeover`` metadata): what the writer is given, in the
service the robot, episode, serving policy version, operator, task, reason, the asking signal and its
threshold (``signal``, ``threshold``: whose score the steps record), ``request`` (the request the
takeover answers: signal, score, threshold, reason, asked_at_step, paper_u; ``Segment.request``) and
``keys.OBS_LABELS``, the observation's channel names in order (segments written before these were
recorded lack them; fine-tuning then judges their observations by size alone, ``storage.takeovers``).
Per step (``/takeover/step``, with the step field names of ``storage.keys`` that episodes use
too): the observation, the operator's command, the resulting absolute
action and the same action in the policy's normalized action space (the fine-tune label), the paper's
U (``uncertainty``) and every other signal's score (``shadow``, the asking signal's included), and the
end-effector pose. ``/tf`` carries the end effector and
``/denoising/field`` the denoising vector field as a ``foxglove.SceneUpdate`` of arrows coloured
by mode. ``/camera/{front,wrist}/image/compressed`` carry the camera views the operator was shown
(``foxglove.CompressedImage``, JPEG; ``frame_id`` names the episode step it shows), when the console
showed them (``server.cameras``). For a policy that sees cameras, ``/observation/images/<camera>`` carry
what each of its cameras saw before each step's action (PNG, as in episodes, ``storage.images``;
``frame_id`` ``step-<t>`` names the takeover step), its cameras listed in the metadata
(``keys.CAMERAS``): the frames fine-tuning trains on (``Segment.frames``). The writer flushes at least
every ``flush_seconds`` (the service: after every step, so a crash of the server loses no step it
applied; docs/service.md, "Durability"); ``read_segment(path, recover=True)`` salvages a file left open
by a crash.
"""

from __future__ import annotations

import base64
import json
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from storage import keys
from storage.images import COMPRESSED_IMAGE_SCHEMA, ImageDecodeError, check_frame, decode_png, png_message
from storage.mcap_io import JsonMcapWriter, read_all, rebuild, salvage, stamp

_COLOURS = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16), (0.58, 0.4, 0.74)]
_OBJ = {"type": "object"}
SCHEMAS = {
    keys.SCHEMA_COMPRESSED_IMAGE: COMPRESSED_IMAGE_SCHEMA,
    keys.SCHEMA_TAKEOVER: _OBJ,
    keys.SCHEMA_TAKEOVER_STEP: _OBJ,
    keys.SCHEMA_TAKEOVER_END: _OBJ,
    keys.SCHEMA_FRAME_TRANSFORM: _OBJ,
    keys.SCHEMA_SCENE_UPDATE: _OBJ,
}


class SegmentReadError(Exception):
    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = path, reason


def _vec(v) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=np.float64).ravel()]


def field_scene_update(ns: int, samples: np.ndarray, vectors: np.ndarray, labels: np.ndarray, scale: float) -> dict:
    """foxglove.SceneUpdate with one arrow per probe sample (world frame), coloured by mode.

    samples: (S, 3) positions (m); vectors: (S, 3) denoising vectors; scale: metres per unit vector.
    """
    samples, vectors = np.asarray(samples, np.float64), np.asarray(vectors, np.float64)
    norms = np.linalg.norm(vectors, axis=1)
    keep = norms > 1e-12
    unit = vectors[keep] / norms[keep, None]
    # an arrow points along its pose's +x axis: the quaternion turning +x onto v is (x × v, 1 + x·v), normalized
    quat = np.stack([np.zeros(len(unit)), -unit[:, 2], unit[:, 1], 1.0 + unit[:, 0]], axis=1)
    opposite = quat[:, 3] < 1e-9
    quat[opposite] = [0.0, 0.0, 1.0, 0.0]  # v = -x: half a turn about z
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    arrows = []
    for p, n, q, k in zip(samples[keep], norms[keep], quat, np.asarray(labels)[keep], strict=True):
        r, g, b = _COLOURS[int(k) % len(_COLOURS)]
        arrows.append(
            {
                "pose": {
                    "position": dict(zip("xyz", _vec(p), strict=True)),
                    "orientation": dict(zip("xyzw", _vec(q), strict=True)),
                },
                "shaft_length": float(n) * scale * 0.8,
                "shaft_diameter": 0.001,
                "head_length": float(n) * scale * 0.2,
                "head_diameter": 0.003,
                "color": {"r": r, "g": g, "b": b, "a": 1.0},
            }
        )
    entity = {"timestamp": stamp(ns), "frame_id": keys.WORLD_FRAME, "id": "denoising_field", "lifetime": stamp(0)}
    return {"deletions": [], "entities": [entity | {"frame_locked": False, "arrows": arrows}]}


class SegmentWriter:
    """Writes one takeover; ``close(status)`` ends it. Flushes at least every ``flush_seconds`` (0: after
    every step, so a crash of the writing process loses no step written); ``fsync``: each flush also
    reaches the disk, so a crash of the machine loses none either."""

    def __init__(self, path: str | Path, meta: dict, flush_seconds: float = 1.0, fsync: bool = False) -> None:
        self.path = Path(path)
        self._mcap = JsonMcapWriter(self.path, SCHEMAS, chunk_size=64 * 1024)
        ch = self._mcap.channel
        self._ch = {
            "meta": ch(keys.TOPIC_TAKEOVER, keys.SCHEMA_TAKEOVER),
            "step": ch(keys.TOPIC_TAKEOVER_STEP, keys.SCHEMA_TAKEOVER_STEP),
            "end": ch(keys.TOPIC_TAKEOVER_END, keys.SCHEMA_TAKEOVER_END),
            "tf": ch(keys.TOPIC_TF, keys.SCHEMA_FRAME_TRANSFORM),
            "field": ch(keys.TOPIC_FIELD, keys.SCHEMA_SCENE_UPDATE),
        }
        self._cameras: dict[str, int] = {}  # camera name -> its channel, opened at its first view
        self.meta = dict(meta)
        self._sizes = {str(c["name"]): int(c["size"]) for c in self.meta.get(keys.CAMERAS) or []}
        self._policy_cameras = {
            name: ch(keys.TOPIC_POLICY_IMAGE.format(name=name), keys.SCHEMA_COMPRESSED_IMAGE) for name in self._sizes
        }
        self.steps = 0
        self._flush_seconds, self._fsync = flush_seconds, fsync
        self._last_flush = time.monotonic()
        self._dirty = False
        self._mcap.add_metadata("takeover", self.meta)
        self._add("meta", time.time_ns(), self.meta)
        self.flush()

    def _add(self, channel: str, ns: int, payload: dict) -> None:
        self._mcap.add(self._ch[channel], ns, payload)

    def write_step(
        self,
        obs: np.ndarray,
        command: dict,
        action: np.ndarray,
        action_normalized: np.ndarray,
        pos: np.ndarray,
        quat: np.ndarray,
        uncertainty: float | None,
        shadow: dict[str, float] | None = None,
        field: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None,
        images: dict[str, np.ndarray] | None = None,
    ) -> None:
        """field: (samples (S, 3) m, vectors (S, 3), labels (S,), arrow scale) for the scene update; images:
        camera -> (size, size, 3) uint8, what each camera the metadata declares (``keys.CAMERAS``) saw before
        the action, every one at every step."""
        images = images or {}
        if set(images) != set(self._sizes):
            raise ValueError(f"frames of cameras {sorted(images)}, the segment declared {sorted(self._sizes)}")
        for name, image in images.items():
            if check_frame(image, name).shape[:2] != (self._sizes[name],) * 2:
                raise ValueError(f"camera {name!r} frame is {np.shape(image)}, declared {self._sizes[name]} pixels")
        ns = time.time_ns()
        for name, image in images.items():
            self._mcap.add(self._policy_cameras[name], ns, png_message(image, f"step-{self.steps}", ns))
        self._add(
            "step",
            ns,
            {
                keys.STEP_T: self.steps,
                keys.STEP_OBSERVATION: _vec(obs),
                "command": command,
                keys.STEP_ACTION: _vec(action),
                "action_normalized": _vec(action_normalized),
                "uncertainty": None if uncertainty is None else float(uncertainty),
                "shadow": {k: float(v) for k, v in (shadow or {}).items()},
                "position": _vec(pos),
                "quaternion": _vec(quat),
            },
        )
        self._add(
            "tf",
            ns,
            {
                "timestamp": stamp(ns),
                "parent_frame_id": keys.WORLD_FRAME,
                "child_frame_id": keys.EE_FRAME,
                "translation": dict(zip("xyz", _vec(pos), strict=True)),
                "rotation": dict(zip("xyzw", _vec(quat), strict=True)),
            },
        )
        if field is not None:
            self._add("field", ns, field_scene_update(ns, *field))
        self.steps += 1
        self._dirty = True
        self.maybe_flush()

    def write_image(self, camera: str, jpeg: bytes, t: int) -> None:
        """One camera view the operator saw: ``camera`` (front, wrist), JPEG bytes, the episode step ``t``
        it shows (its ``frame_id``: ``step-<t>``)."""
        if camera not in self._cameras:
            topic = keys.TOPIC_CAMERA.format(name=camera)
            self._cameras[camera] = self._mcap.channel(topic, keys.SCHEMA_COMPRESSED_IMAGE)
        ns = time.time_ns()
        payload = {
            "timestamp": stamp(ns),
            "frame_id": f"step-{int(t)}",
            "data": base64.b64encode(jpeg).decode("ascii"),
            "format": "jpeg",
        }
        self._mcap.add(self._cameras[camera], ns, payload)
        self._dirty = True  # flushed with the steps (the control loop's flush_takeover), not here

    def maybe_flush(self) -> None:
        """Flushes unwritten steps older than ``flush_seconds``; call it periodically (the control loop does)."""
        if self._dirty and time.monotonic() - self._last_flush >= self._flush_seconds:
            self.flush()

    def flush(self) -> None:
        self._mcap.flush(sync=self._fsync)
        self._last_flush = time.monotonic()
        self._dirty = False

    def close(self, status: str = "closed", ended_by: str | None = None) -> None:
        """Writes the end message (status, why the takeover ended, steps) and the file's index."""
        if self._mcap.closed:
            return
        try:
            self._add("end", time.time_ns(), end_message(status, ended_by, self.steps))
        finally:
            self._mcap.close()


def end_message(status: str, ended_by: str | None, steps: int) -> dict:
    """The ``/takeover/end`` payload: status (closed, recovered), ended_by (hand-back, lease-expired,
    episode-ended, worker-fault, reset, service-stopped, crash-recovered) and the steps recorded."""
    return {"status": status, "ended_by": ended_by, "steps": int(steps)}


def recover_segment(path: str | Path) -> int:
    """Rewrites a segment left open by a crash as a complete, indexed MCAP with an end message
    (``recovered``, ``crash-recovered``); returns the steps it keeps. Raises SegmentReadError when
    nothing of the file is readable."""
    path = Path(path)
    if not path.is_file():
        raise SegmentReadError(path, "no such file")
    try:
        seg = read_segment(path, recover=True)
    except SegmentReadError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise SegmentReadError(path, f"unreadable ({type(exc).__name__}: {exc})") from exc
    steps = len(seg.step_messages)  # counted, not read: recovery keeps whatever the file holds
    if seg.end is not None and not seg.recovered:
        return steps  # already complete
    # a file that lost only its footer already has its end message: it is indexed, not given a second one
    end = None if seg.end is not None else end_message("recovered", "crash-recovered", steps)
    rebuild(path, {keys.TOPIC_TAKEOVER_END: end} if end is not None else None)
    return steps


@dataclass(frozen=True)
class SegmentStep:
    """One ``/takeover/step`` as read: t (its index in the takeover), observation (obs_dim,), the
    operator's command (delta_pos, delta_rot, gripper), the absolute action (10,) it produced and the
    same in the serving policy's normalized action space, U (None: not scored), the shadow signals'
    scores, the end effector's position (3,) and quaternion (4, x y z w) before the action. Values are
    as the file holds them (JSON lists); a reader checks their shapes."""

    observation: list[float]
    action: list[float]
    position: list[float]
    quaternion: list[float]
    t: int | None = None
    command: dict | None = None
    action_normalized: list[float] | None = None
    uncertainty: float | None = None
    shadow: dict[str, float] = field(default_factory=dict)

    @classmethod
    def from_message(cls, doc: dict) -> SegmentStep:
        """Raises KeyError or TypeError for a message without the fields every step has."""
        return cls(
            observation=doc[keys.STEP_OBSERVATION],
            action=doc[keys.STEP_ACTION],
            position=doc["position"],
            quaternion=doc["quaternion"],
            t=doc.get(keys.STEP_T),
            command=doc.get("command"),
            action_normalized=doc.get("action_normalized"),
            uncertainty=doc.get("uncertainty"),
            shadow=doc.get("shadow") or {},
        )


@dataclass
class Segment:
    """A read segment: ``meta`` (/takeover), ``steps`` (/takeover/step, typed when first read: a step
    without the fields every step has raises SegmentReadError then), ``end`` (/takeover/end, None while
    open), ``recovered`` (salvaged from a file left open), ``fields`` (a foxglove.SceneUpdate per step),
    ``images`` (per camera, the views the operator saw; ``Segment.jpeg`` decodes one)."""

    path: Path
    meta: dict
    end: dict | None = None
    recovered: bool = False
    fields: list[dict] = field(default_factory=list)
    images: dict[str, list[dict]] = field(default_factory=dict)  # camera -> its foxglove.CompressedImage messages
    policy_images: dict[str, list[dict]] = field(default_factory=dict)  # camera -> what the policy saw (``frames``)
    step_messages: list[dict] = field(default_factory=list, repr=False)  # the /takeover/step payloads

    @property
    def request(self) -> dict | None:
        """The request the takeover answers (signal, score, threshold, reason, asked_at_step, paper_u);
        None for a segment written before it was recorded."""
        req = self.meta.get("request")
        return req if isinstance(req, dict) else None

    @staticmethod
    def jpeg(message: dict) -> bytes:
        """The JPEG bytes of one ``images`` message."""
        return base64.b64decode(message["data"])

    @cached_property
    def steps(self) -> tuple[SegmentStep, ...]:
        try:
            return tuple(SegmentStep.from_message(doc) for doc in self.step_messages)
        except (KeyError, TypeError, ValueError) as exc:
            raise SegmentReadError(self.path, f"malformed step ({type(exc).__name__}: {exc})") from exc

    def frames(self, camera: str) -> np.ndarray:
        """(T, size, size, 3) uint8: what the policy's ``camera`` saw at each step (``keys.CAMERAS``).
        SegmentReadError when the segment lacks the camera, a step's frame, or a frame is not a PNG."""
        spec = next((c for c in self.meta.get(keys.CAMERAS) or [] if c.get("name") == camera), None)
        if spec is None:
            raise SegmentReadError(
                self.path, f"no frames of camera {camera!r} (the policy's cameras were not recorded)"
            )
        by_step = {m.get("frame_id"): m for m in self.policy_images.get(camera, [])}
        size = (int(spec["size"]),) * 2
        out = []
        for t in range(len(self.step_messages)):
            message = by_step.get(f"step-{t}")
            if message is None:
                raise SegmentReadError(self.path, f"camera {camera!r}: no frame of step {t}")
            try:
                out.append(decode_png(message, size))
            except ImageDecodeError as exc:
                raise SegmentReadError(self.path, f"camera {camera!r}, step {t}: {exc}") from exc
        return np.stack(out) if out else np.zeros((0, *size, 3), np.uint8)

    def labels(self) -> tuple[np.ndarray, np.ndarray]:
        """(obs (T, obs_dim), normalized action labels (T, 10)) for fine-tuning."""
        return (
            np.array([s.observation for s in self.steps], dtype=np.float32),
            np.array([s.action_normalized for s in self.steps], dtype=np.float32),
        )


def _collect(path: Path, messages, recovered: bool) -> Segment:
    seg = Segment(path, {}, recovered=recovered)
    for _schema, channel, message in messages:
        doc = json.loads(message.data)
        if channel.topic == keys.TOPIC_TAKEOVER:
            seg.meta = doc
        elif channel.topic == keys.TOPIC_TAKEOVER_STEP:
            seg.step_messages.append(doc)
        elif channel.topic == keys.TOPIC_TAKEOVER_END:
            seg.end = doc
        elif channel.topic == keys.TOPIC_FIELD:
            seg.fields.append(doc)
        elif channel.topic.startswith(keys.TOPIC_POLICY_IMAGE.format(name="")):
            seg.policy_images.setdefault(channel.topic.rsplit("/", 1)[1], []).append(doc)
        elif channel.topic.startswith("/camera/") and channel.topic.endswith("/image/compressed"):
            seg.images.setdefault(channel.topic.split("/")[2], []).append(doc)
    if not seg.meta:
        raise SegmentReadError(path, "no /takeover message: not a takeover segment")
    return seg


def read_segment(path: str | Path, recover: bool = False) -> Segment:
    """Reads a segment; ``recover`` salvages what was flushed from a file left open by a crash."""
    path = Path(path)
    if not path.is_file():
        raise SegmentReadError(path, "no such file")
    try:
        return _collect(path, read_all(path), False)
    except SegmentReadError:
        raise
    except Exception as exc:  # noqa: BLE001 - mcap raises several types for broken files
        if not recover:
            raise SegmentReadError(
                path, f"truncated or corrupt ({type(exc).__name__}: {exc}); use recover=True"
            ) from exc
    out, _ = salvage(path)
    if not out:
        raise SegmentReadError(path, "nothing recoverable")
    return _collect(path, out, True)

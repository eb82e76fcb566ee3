"""Task attempts as frame tables: what one LeRobot episode holds, built from our MCAP files.

An ``Attempt`` is one episode of the exported dataset: per frame the observation, the end-effector
pose and finger gap, the absolute action executed, who produced it (``keys.SOURCES``), the operator's
command on an operator step, the asking signal's score and threshold where the robot was scored, the
policy version that drove it, and the takeover (segment id) an operator step belongs to with that
takeover's label. ``from_episode`` builds one from a whole recorded episode (its takeovers inside it,
marked frame by frame); ``from_segment`` from one takeover segment alone (the takeover-only export,
and takeovers whose episode was not recorded).
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from storage import keys
from storage.episodes import Episode, read_episode
from storage.segments import Segment, SegmentStep

COMMAND_DIM = 7  # delta_pos (3), delta_rot (3), gripper
LABEL_CODES = {"good": 1, "bad": -1, None: 0}  # the per-frame code of a takeover's label
NO_TAKEOVER = -1


@dataclass(frozen=True)
class TakeoverRequest:
    """The assistance request a takeover answered: the asking signal's name ("watchdog" when the watchdog
    asked, None for help requested through the service or not recorded), its score and threshold, the
    reason the queue showed, and the paper's denoising U then. None where not recorded (takeovers
    recorded before the service stored them)."""

    signal: str | None = None
    score: float | None = None
    threshold: float | None = None
    reason: str | None = None
    paper_u: float | None = None

    def as_dict(self) -> dict:
        return {
            "signal": self.signal,
            "score": self.score,
            "threshold": self.threshold,
            "reason": self.reason,
            "paper_u": self.paper_u,
        }


@dataclass(frozen=True)
class TakeoverLabel:
    """An operator's verdict on one takeover: label (good, bad or None), discarded (kept on disk, never
    trained on), a short note, who set it and when; and the request it answered (None: not known)."""

    label: str | None = None
    discarded: bool = False
    note: str | None = None
    labelled_by: str | None = None
    labelled_at: datetime | None = None
    request: TakeoverRequest | None = None

    def as_dict(self) -> dict:
        return {
            "label": self.label,
            "discarded": self.discarded,
            "note": self.note,
            "labelled_by": self.labelled_by,
            "labelled_at": None if self.labelled_at is None else self.labelled_at.isoformat(),
            "request": None if self.request is None else self.request.as_dict(),
        }


@dataclass
class Attempt:
    """One exported episode. Arrays have one row per frame (T); ``meta`` is per episode."""

    task: str
    kind: str  # "episode" (a whole task attempt) or "takeover" (one takeover segment alone)
    source: str  # the file it came from (name only)
    obs: np.ndarray  # (T, obs_dim)
    ee_pose: np.ndarray  # (T, 7) position + quaternion xyzw
    gripper: np.ndarray  # (T,) finger gap (m)
    action: np.ndarray  # (T, 10)
    success: np.ndarray  # (T,) bool: the task succeeded after this frame
    action_source: np.ndarray  # (T,) int64, index into keys.SOURCES
    command: np.ndarray  # (T, 7) the operator's command (zeros where there was none)
    scored: np.ndarray  # (T,) bool
    score: np.ndarray  # (T,) the asking signal's score (0 where not scored)
    threshold: np.ndarray  # (T,)
    policy_version: np.ndarray  # (T,) int64 registry id (0: none, e.g. a scripted demonstration)
    takeover: np.ndarray  # (T,) int64 segment id (NO_TAKEOVER: none)
    obs_labels: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)  # seed, robot, fleet episode id, outcome, policy, signal, ...
    takeovers: dict[int, TakeoverLabel] = field(default_factory=dict)  # segment id -> its label
    # what a policy that sees saw: camera -> one PNG per frame (the recorded bytes, not decoded), and their specs
    images: dict[str, list[bytes]] = field(default_factory=dict)
    cameras: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.action)

    @property
    def intervention(self) -> np.ndarray:
        return self.action_source == keys.SOURCES.index(keys.SOURCE_OPERATOR)

    def label_codes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per frame: the takeover's label code (LABEL_CODES) and whether it was discarded."""
        codes, discarded = np.zeros(len(self), np.int64), np.zeros(len(self), bool)
        for sid, lab in self.takeovers.items():
            rows = self.takeover == sid
            codes[rows], discarded[rows] = LABEL_CODES[lab.label], lab.discarded
        return codes, discarded


def _command_row(command: dict | None) -> list[float]:
    if not command:
        return [0.0] * COMMAND_DIM
    return [*map(float, command["delta_pos"]), *map(float, command["delta_rot"]), float(command["gripper"] or 0.0)]


def from_episode(ep: Episode, labels: dict[int, TakeoverLabel] | None = None, meta: dict | None = None) -> Attempt:
    """A whole recorded episode; ``labels``: segment id -> label for the takeovers inside it."""
    n = len(ep)
    extras = ep.extras or [{} for _ in range(n)]
    scored = np.array([keys.STEP_SCORE in e for e in extras], bool)
    takeover = np.array([e.get(keys.STEP_TAKEOVER, NO_TAKEOVER) for e in extras], np.int64)
    fallback_version = int(ep.meta.get("policy_version") or 0)
    present = {int(t) for t in takeover if t != NO_TAKEOVER}
    return Attempt(
        task=str(ep.meta.get("task", "")),
        kind="episode",
        source=ep.path.name,
        obs=ep.obs,
        ee_pose=ep.ee_pose,
        gripper=ep.gripper,
        action=ep.actions,
        success=ep.success.astype(bool),
        action_source=np.array([keys.SOURCES.index(s) for s in ep.sources], np.int64),
        command=np.array([_command_row(e.get(keys.STEP_COMMAND)) for e in extras], np.float64).reshape(n, COMMAND_DIM),
        scored=scored,
        score=np.array([e.get(keys.STEP_SCORE, 0.0) for e in extras], np.float64),
        threshold=np.array([e.get(keys.STEP_THRESHOLD, 0.0) for e in extras], np.float64),
        policy_version=np.array([e.get(keys.STEP_POLICY_VERSION, fallback_version) for e in extras], np.int64),
        takeover=takeover,
        obs_labels=list(ep.meta.get("obs_labels") or []),
        meta={
            "seed": ep.meta.get("seed"),
            "robot": ep.meta.get("robot"),
            "outcome": (ep.outcome or {}).get("reason"),
        }
        | (meta or {}),
        takeovers={sid: (labels or {}).get(sid, TakeoverLabel()) for sid in sorted(present)},
        images={c["name"]: [_png(m) for m in ep.images.get(c["name"], [])] for c in ep.cameras},
        cameras=ep.cameras,
    )


def _png(message: dict) -> bytes:
    return base64.b64decode(message["data"])


def from_segment(
    seg: Segment, segment_id: int, label: TakeoverLabel | None = None, meta: dict | None = None
) -> Attempt:
    """One takeover on its own: every frame an operator step (``next.success`` false: a segment does not
    record the task's success)."""
    steps = seg.steps
    n = len(steps)
    signal = seg.meta.get("signal")
    threshold = seg.meta.get("threshold")

    def score(s: SegmentStep) -> float | None:
        scores = {"denoising": s.uncertainty} | s.shadow
        return scores.get(signal) if signal else None

    scores = [score(s) for s in steps]
    return Attempt(
        task=str(seg.meta.get("task", "")),
        kind="takeover",
        source=seg.path.name,
        obs=np.array([s.observation for s in steps], np.float64).reshape(n, -1),
        ee_pose=np.array([list(s.position) + list(s.quaternion) for s in steps], np.float64).reshape(n, 7),
        gripper=np.zeros(n),  # not in a segment's steps
        action=np.array([s.action for s in steps], np.float64).reshape(n, -1),
        success=np.zeros(n, bool),
        action_source=np.full(n, keys.SOURCES.index(keys.SOURCE_OPERATOR), np.int64),
        command=np.array([_command_row(s.command) for s in steps], np.float64).reshape(n, COMMAND_DIM),
        scored=np.array([v is not None and threshold is not None for v in scores], bool),
        score=np.array([v if v is not None and threshold is not None else 0.0 for v in scores], np.float64),
        threshold=np.full(n, float(threshold) if threshold is not None else 0.0),
        policy_version=np.full(n, int(seg.meta.get("policy_version") or 0), np.int64),
        takeover=np.full(n, segment_id, np.int64),
        obs_labels=list(seg.meta.get(keys.OBS_LABELS) or []),  # segments written before they recorded it: none
        meta={"seed": seg.meta.get("seed"), "robot": seg.meta.get("robot"), "episode": seg.meta.get("episode")}
        | (meta or {}),
        takeovers={segment_id: label or TakeoverLabel()},
        images={c["name"]: _segment_pngs(seg, c["name"], n) for c in seg.meta.get(keys.CAMERAS) or []},
        cameras=list(seg.meta.get(keys.CAMERAS) or []),
    )


def _segment_pngs(seg: Segment, camera: str, n: int) -> list[bytes]:
    by_step = {m.get("frame_id"): m for m in seg.policy_images.get(camera, [])}
    return [_png(by_step[f"step-{t}"]) for t in range(n) if f"step-{t}" in by_step]


def from_folder(folder: str | Path, task: str | None = None) -> list[Attempt]:
    """Every episode file in a folder (``hitl demos`` output, or the fleet's ``episodes/``), by name;
    ``task``: only that task's. A file that cannot be read raises ``EpisodeReadError``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    attempts = [from_episode(read_episode(f)) for f in sorted(folder.glob(keys.EPISODE_GLOB))]
    return [a for a in attempts if task is None or a.task == task]

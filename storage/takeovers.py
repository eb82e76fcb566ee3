"""Takeover segments as fine-tuning data: (observation history, operator action chunk) pairs.

The label is the absolute action the operator's command produced (``/takeover/step`` ``action``), in
the policy's own absolute action space: the version being fine-tuned normalizes it with its own
normalizer when it trains, whatever version served the segment (the segment's ``action_normalized``
is the serving version's and is not used). Each segment is one contiguous sequence, windowed like a
demonstration episode (``storage.dataset``): histories padded with the first observation, chunks
with the last action.

A segment that cannot be used (unreadable, truncated, empty, wrong dimensions, recorded with another
observation layout than the policy's, non-finite values) is skipped, and ``TakeoverSet.skipped`` names it
with the reason: the caller reports it, nothing fails silently. A segment of another layout is left out,
not fatal: a lineage keeps the segments of its earlier versions, and those of a layout since changed
must not stop every later job; the job fails when no usable segment is left, naming them.

``TakeoverSelection`` says which takeovers and steps to learn from: only takeovers whose episode ended
in success (``successful_only``: the operator's help led somewhere; the caller, which knows the
episodes' outcomes, leaves the others out), and of each only its last ``tail`` steps, the ones that led
to the hand-back (``load_takeovers`` cuts them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage import keys
from storage.dataset import DatasetConfig, DemoDataset
from storage.obs_layout import describe, difference, recorded
from storage.segments import SegmentReadError, read_segment

ACTION_DIM = 10
SUCCESS = "success"  # the episode outcome a successful_only selection keeps (server.db.EpisodeRecord.outcome)


@dataclass(frozen=True)
class TakeoverSelection:
    """Which takeovers and steps to learn from. successful_only: only takeovers whose episode ended in
    success (not in a timeout, a fault, a reset, a shutdown); tail: of each takeover only its last
    ``tail`` steps (None: all of them)."""

    successful_only: bool = False
    tail: int | None = None

    def __post_init__(self) -> None:
        t = self.tail
        if t is not None and (not isinstance(t, int) or isinstance(t, bool) or t < 1):
            raise ValueError(f"takeover tail must be an integer >= 1 or None, got {t!r}")

    def why_excluded(self, outcome: str | None) -> str | None:
        """None when a takeover whose episode ended with ``outcome`` (None: not ended) is kept; otherwise
        why the selection leaves it out."""
        if not self.successful_only or outcome == SUCCESS:
            return None
        if outcome is None:
            return "its episode has not ended (successful episodes only)"
        return f"its episode ended in {outcome} (successful episodes only)"

    def steps(self, n: int) -> slice:
        """The steps kept of an n-step takeover."""
        return slice(max(0, n - self.tail), n) if self.tail is not None else slice(0, n)


@dataclass
class TakeoverSet:
    """obs: (N, obs_dim) and actions: (N, 10) per step, segments concatenated (``episode_ends``);
    used: the segment files used, in order; skipped: file -> why it was not used."""

    obs: np.ndarray
    actions: np.ndarray
    ee_pose: np.ndarray
    episode_ends: np.ndarray
    used: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)  # camera -> (N, size, size, 3) uint8 the policy saw

    def __len__(self) -> int:
        return len(self.obs)

    def arrays(self, obs_horizon: int, action_horizon: int) -> dict[str, np.ndarray]:
        """{OBS: (N, H, obs_dim), ACTION: (N, C, 10)} and each camera's frames (``keys.image_key``: (N, H,
        size, size, 3) uint8): one sample per takeover step."""
        if not len(self):
            return {
                keys.OBS: np.zeros((0, obs_horizon, self.obs.shape[1]), np.float32),
                keys.ACTION: np.zeros((0, action_horizon, ACTION_DIM), np.float32),
                **{
                    keys.image_key(c): np.zeros((0, obs_horizon, *im.shape[1:]), np.uint8)
                    for c, im in self.images.items()
                },
            }
        ds = DemoDataset(
            folder=Path("."),
            config=DatasetConfig(obs_horizon=obs_horizon, action_horizon=action_horizon, val_fraction=0.0, cache=False),
            obs=self.obs,
            actions=self.actions,
            ee_pose=self.ee_pose,
            episode_ends=self.episode_ends,
            names=self.used,
            meta=[{} for _ in self.used],
            excluded={},
            images=self.images,
        )
        return ds.arrays("all")


def _steps(
    path: Path, obs_dim: int, obs_labels: list[str] | None, cameras: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    seg = read_segment(path)  # closed and recovered segments are complete files
    if (
        obs_labels is not None
        and (labels := recorded(seg.meta)) is not None
        and (diff := difference(obs_labels, labels))
    ):
        where = f"task {seg.meta.get('task', '?')}, observations {describe(labels)}"
        raise SegmentReadError(
            path, f"recorded with another observation layout than the policy's ({where}): " + "; ".join(diff)
        )
    if seg.end is None:
        raise SegmentReadError(path, "no /takeover/end message: the segment is still open")
    steps = seg.steps  # a step without the fields every step has: SegmentReadError (malformed step)
    if not steps:
        raise SegmentReadError(path, "no steps")
    try:
        obs = np.array([s.observation for s in steps], dtype=np.float32)
        act = np.array([s.action for s in steps], dtype=np.float32)
        pose = np.array([list(s.position) + list(s.quaternion) for s in steps], dtype=np.float32)
    except (KeyError, TypeError, ValueError) as exc:
        raise SegmentReadError(path, f"malformed step ({type(exc).__name__}: {exc})") from exc
    if obs.ndim != 2 or obs.shape[1] != obs_dim:
        raise SegmentReadError(path, f"observations of shape {obs.shape}, the policy takes {obs_dim} per step")
    if act.ndim != 2 or act.shape[1] != ACTION_DIM:
        raise SegmentReadError(path, f"actions of shape {act.shape}, expected (T, {ACTION_DIM})")
    if pose.ndim != 2 or pose.shape[1] != 7:
        raise SegmentReadError(path, f"poses of shape {pose.shape}, expected (T, 7)")
    if not (np.isfinite(obs).all() and np.isfinite(act).all()):
        raise SegmentReadError(path, "non-finite observation or action values")
    return obs, act, pose, {c: seg.frames(c) for c in cameras}


def load_takeovers(
    paths: list[Path],
    obs_dim: int,
    selection: TakeoverSelection | None = None,
    obs_labels: list[str] | None = None,
    cameras: list[str] | tuple[str, ...] = (),
) -> TakeoverSet:
    """Reads every segment in ``paths`` (in order); unusable ones are listed in ``skipped``. Of each
    usable one the steps ``selection`` keeps (its tail; which segments to pass is the caller's).
    ``obs_labels``: the observation layout the policy takes (``storage.obs_layout``); a segment recorded
    with another one is unusable, its reason naming the channels that differ (one that records none,
    written before segments did, is judged by its observations' size alone). ``cameras``: those the policy
    sees; a segment without their frames at every step is unusable (``Segment.frames``)."""
    selection = selection or TakeoverSelection()
    obs, act, pose, ends, used, skipped = [], [], [], [], [], {}
    frames: dict[str, list[np.ndarray]] = {c: [] for c in cameras}
    for path in paths:
        path = Path(path)
        try:
            o, a, p, f = _steps(path, obs_dim, obs_labels, list(cameras))
        except SegmentReadError as exc:
            skipped[path.name] = exc.reason
            continue
        except Exception as exc:  # noqa: BLE001 - any other failure of one file is that file's problem
            skipped[path.name] = f"unreadable ({type(exc).__name__}: {exc})"
            continue
        keep = selection.steps(len(o))
        o, a, p = o[keep], a[keep], p[keep]
        for c in cameras:
            frames[c].append(f[c][keep])
        obs.append(o)
        act.append(a)
        pose.append(p)
        ends.append(len(o))
        used.append(path.name)
    if not obs:
        return TakeoverSet(
            np.zeros((0, obs_dim), np.float32),
            np.zeros((0, ACTION_DIM), np.float32),
            np.zeros((0, 7), np.float32),
            np.zeros(0, np.int64),
            used,
            skipped,
        )
    return TakeoverSet(
        np.concatenate(obs),
        np.concatenate(act),
        np.concatenate(pose),
        np.cumsum(ends).astype(np.int64),
        used,
        skipped,
        {c: np.concatenate(v) for c, v in frames.items()},
    )

"""Demonstration datasets: a folder of MCAP episodes as training arrays.

Sample indexing (as in diffusion_policy): every control step ``t`` of an
episode spanning rows ``[s, e)`` is one sample with

- observation history ``obs[t - H + 1 .. t]``, rows before ``s`` padded with ``obs[s]``;
- action chunk ``actions[t .. t + C - 1]``, rows from ``e`` on padded with ``actions[e - 1]``.

The validation split is by episode, chosen with a seeded shuffle. A decoded
copy is cached under ``<folder>/.cache/`` keyed by the files' names, sizes and
modification times, so the second load skips MCAP decoding. Episodes recorded
for a policy that sees cameras carry their frames (``storage.episodes``): they
are decoded from PNG once, into one ``.npy`` per camera in the cache, which
later loads map from disk instead of decoding again (``DemoDataset.images``).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage import keys
from storage.episodes import EpisodeReadError, read_episode


class DatasetError(Exception):
    """One or more episode files could not be used; the message names each one."""

    def __init__(self, folder: Path, problems: dict[str, str]) -> None:
        self.folder = folder
        self.problems = problems
        lines = "\n".join(f"  {name}: {why}" for name, why in sorted(problems.items()))
        super().__init__(f"{len(problems)} bad episode file(s) in {folder}:\n{lines}")


@dataclass(frozen=True)
class DatasetConfig:
    """obs_horizon H (>= 1), action_horizon C (>= 1), validation fraction by episode."""

    obs_horizon: int = 1
    action_horizon: int = 1
    val_fraction: float = 0.1
    split_seed: int = 0
    successful_only: bool = True
    recover: bool = False  # use episodes salvaged from truncated files
    cache: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.obs_horizon, int) and self.obs_horizon >= 1):
            raise ValueError(f"obs_horizon must be an integer >= 1, got {self.obs_horizon!r}")
        if not (isinstance(self.action_horizon, int) and self.action_horizon >= 1):
            raise ValueError(f"action_horizon must be an integer >= 1, got {self.action_horizon!r}")
        if not (isinstance(self.val_fraction, int | float) and 0 <= self.val_fraction < 1):
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction!r}")


@dataclass
class DemoDataset:
    """All steps of all episodes, concatenated.

    obs: (N, obs_dim) float32; actions: (N, 10) float32; episode_ends: (E,)
    exclusive end row of each episode; names: (E,) file names; meta: per episode;
    images: camera -> (N, size, size, 3) uint8, what it saw at each row (empty for
    state-only episodes); cameras: their specs as recorded (name, size, crop).
    """

    folder: Path
    config: DatasetConfig
    obs: np.ndarray
    actions: np.ndarray
    ee_pose: np.ndarray
    episode_ends: np.ndarray
    names: list[str]
    meta: list[dict]
    excluded: dict[str, str]
    from_cache: bool = False
    images: dict[str, np.ndarray] = field(default_factory=dict)
    cameras: list[dict] = field(default_factory=list)

    @property
    def episode_starts(self) -> np.ndarray:
        return np.concatenate([[0], self.episode_ends[:-1]]).astype(np.int64)

    @property
    def num_episodes(self) -> int:
        return len(self.episode_ends)

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(train episode ids, validation episode ids); validation is never empty if E >= 2."""
        n = self.num_episodes
        order = np.random.default_rng(self.config.split_seed).permutation(n)
        n_val = math.ceil(n * self.config.val_fraction) if self.config.val_fraction > 0 else 0
        n_val = min(n_val, max(n - 1, 0))
        return np.sort(order[n_val:]), np.sort(order[:n_val])

    def sample_index(self, episodes: np.ndarray) -> np.ndarray:
        """(M, 3) rows of (t, episode start, episode end) for every step of ``episodes``."""
        starts, ends = self.episode_starts, self.episode_ends
        rows = [
            np.stack(
                [
                    np.arange(starts[e], ends[e]),
                    np.full(ends[e] - starts[e], starts[e]),
                    np.full(ends[e] - starts[e], ends[e]),
                ],
                axis=1,
            )
            for e in episodes
        ]
        return np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 3), np.int64)

    def windows(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gathers (M, H, obs_dim) observation histories and (M, C, 10) action chunks."""
        t, start, end = index[:, 0:1], index[:, 1:2], index[:, 2:3]
        h, c = self.config.obs_horizon, self.config.action_horizon
        obs_rows = np.clip(t + np.arange(-h + 1, 1), start, None)
        act_rows = np.clip(t + np.arange(c), None, end - 1)
        return self.obs[obs_rows], self.actions[act_rows]

    def image_windows(self, index: np.ndarray) -> dict[str, np.ndarray]:
        """{``keys.image_key(camera)``: (M, H, size, size, 3) uint8} for each camera: the frames of the
        observation histories ``windows`` gathers (empty for state-only data)."""
        t, start = index[:, 0:1], index[:, 1:2]
        rows = np.clip(t + np.arange(-self.config.obs_horizon + 1, 1), start, None)
        return {keys.image_key(name): np.asarray(frames[rows]) for name, frames in self.images.items()}

    def arrays(self, split: str = "train") -> dict[str, np.ndarray]:
        """{OBS: (M, H, obs_dim), ACTION: (M, C, 10)} and each camera's frames (``image_windows``) for
        ``split`` in {"train", "val", "all"}."""
        train, val = self.split()
        episodes = {"train": train, "val": val, "all": np.arange(self.num_episodes)}[split]
        index = self.sample_index(episodes)
        obs, act = self.windows(index)
        return {keys.OBS: obs, keys.ACTION: act, **self.image_windows(index)}


def _fingerprint(files: list[Path], config: DatasetConfig) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([config.successful_only, config.recover]).encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:20]


def load_dataset(folder: str | Path, config: DatasetConfig | None = None) -> DemoDataset:
    """Loads every ``*.mcap`` episode in ``folder``.

    Raises ``DatasetError`` naming each corrupt, truncated or unfinished file
    (with ``recover=True`` truncated files contribute what was flushed).
    Unsuccessful episodes are left out when ``successful_only`` and listed in
    ``DemoDataset.excluded``.
    """
    config = config or DatasetConfig()
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"dataset folder {folder} does not exist")
    files = sorted(folder.glob(keys.EPISODE_GLOB))
    if not files:
        raise FileNotFoundError(f"no {keys.EPISODE_GLOB} episodes in {folder}")
    cache_file = folder / keys.CACHE_DIR / f"decoded-{_fingerprint(files, config)}.npz"
    if config.cache and cache_file.exists():
        try:
            return _from_cache(folder, config, cache_file)
        except (OSError, ValueError, KeyError):
            cache_file.unlink(missing_ok=True)  # a damaged cache is rebuilt from the episodes

    problems: dict[str, str] = {}
    excluded: dict[str, str] = {}
    episodes = []
    for f in files:
        try:
            ep = read_episode(f, recover=config.recover)
        except EpisodeReadError as exc:
            problems[f.name] = exc.reason
            continue
        if ep.outcome is None and not ep.recovered:
            problems[f.name] = "no /outcome message: the recording was closed without finishing"
            continue
        if len(ep) == 0:
            problems[f.name] = "no steps"
            continue
        if config.successful_only and not (ep.success.any()):
            excluded[f.name] = "unsuccessful"
            continue
        episodes.append(ep)
    if problems:
        raise DatasetError(folder, problems)
    if not episodes:
        raise DatasetError(folder, {f.name: excluded.get(f.name, "unusable") for f in files})
    dims = {(ep.obs.shape[1], ep.actions.shape[1]) for ep in episodes}
    if len(dims) != 1:
        raise DatasetError(
            folder, {ep.path.name: f"obs/action dims {ep.obs.shape[1]}/{ep.actions.shape[1]}" for ep in episodes}
        )
    cameras = _cameras(folder, episodes)
    images = {}
    for cam in cameras:
        frames, bad = [], {}
        for ep in episodes:
            try:
                frames.append(ep.frames(cam["name"]))
            except EpisodeReadError as exc:
                bad[ep.path.name] = exc.reason
        if bad:
            raise DatasetError(folder, bad)
        images[cam["name"]] = np.concatenate(frames)
    ds = DemoDataset(
        folder=folder,
        config=config,
        obs=np.concatenate([ep.obs for ep in episodes]).astype(np.float32),
        actions=np.concatenate([ep.actions for ep in episodes]).astype(np.float32),
        ee_pose=np.concatenate([ep.ee_pose for ep in episodes]).astype(np.float32),
        episode_ends=np.cumsum([len(ep) for ep in episodes]).astype(np.int64),
        names=[ep.path.name for ep in episodes],
        meta=[ep.meta | {"recovered": ep.recovered} for ep in episodes],
        excluded=excluded,
        images=images,
        cameras=cameras,
    )
    if config.cache:
        _to_cache(ds, cache_file)
    return ds


def _cameras(folder: Path, episodes: list) -> list[dict]:
    """The cameras every episode recorded, the same in each (DatasetError naming those that differ)."""
    first = episodes[0].cameras
    other = {
        ep.path.name: f"recorded cameras {ep.cameras}, not {first} like {episodes[0].path.name}"
        for ep in episodes
        if ep.cameras != first
    }
    if other:
        raise DatasetError(folder, other)
    return first


def _to_cache(ds: DemoDataset, cache_file: Path) -> None:
    cache_file.parent.mkdir(exist_ok=True)
    for old in cache_file.parent.glob("decoded-*"):
        old.unlink(missing_ok=True)
    for name, frames in ds.images.items():  # before the index file: a cache without its frames is not found
        part = _frames_file(cache_file, name)
        tmp = part.with_suffix(".tmp.npy")
        np.save(tmp, frames)
        tmp.replace(part)
    tmp = cache_file.with_suffix(".tmp.npz")
    np.savez(
        tmp,
        obs=ds.obs,
        actions=ds.actions,
        ee_pose=ds.ee_pose,
        episode_ends=ds.episode_ends,
        info=np.array(json.dumps({"names": ds.names, "meta": ds.meta, "excluded": ds.excluded, "cameras": ds.cameras})),
    )
    tmp.replace(cache_file)


def _from_cache(folder: Path, config: DatasetConfig, cache_file: Path) -> DemoDataset:
    with np.load(cache_file, allow_pickle=False) as z:
        info = json.loads(str(z["info"]))
        cameras = info.get("cameras", [])
        images = {}
        for cam in cameras:  # mapped, not read: a training run touches the rows it samples
            images[cam["name"]] = np.load(_frames_file(cache_file, cam["name"]), mmap_mode="r", allow_pickle=False)
            if len(images[cam["name"]]) != len(z["obs"]):
                raise ValueError(f"cached frames of {cam['name']} do not match the cached steps")
        return DemoDataset(
            folder=folder,
            config=config,
            obs=z["obs"],
            actions=z["actions"],
            ee_pose=z["ee_pose"],
            episode_ends=z["episode_ends"],
            names=info["names"],
            meta=info["meta"],
            excluded=info["excluded"],
            from_cache=True,
            images=images,
            cameras=cameras,
        )


def _frames_file(cache_file: Path, camera: str) -> Path:
    return cache_file.with_name(f"{cache_file.stem}.{camera}.npy")

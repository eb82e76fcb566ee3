"""``hitl bench finetune``: the paper's fine-tuning figure on our lift tasks.

From one pretrained lift policy: collect fine-tuning data on the unseen objects from each source,

- ``takeover:<signal>``: the operator's steps (the scripted expert through the operator view) in
  assisted rollouts where ``<signal>`` asks for help, with the demo fleet's hand-back rules
  (continuous, cooldown 10; ``hand_back="operator"``: the operator keeps control until the object
  is held, ``Expert.holding``), whole takeovers drawn in a seeded random order;
- ``full-trajectory``: whole scripted-expert demonstrations, one after the other;
- ``expert:grasp``: the same demonstrations cut to the steps around the grasp (``GRASP_WINDOW``): the
  data of a signal that asks exactly at the grasp and an operator who hands back once the object is
  held. No signal collects it; it tells what perfect timing would be worth;

then, for each source and each sample count K, fine-tune a copy of the policy on the first K samples
(spread evenly over the unseen tasks; of takeovers, the steps the recipe's ``TakeoverSelection`` keeps:
with ``successful_only`` only takeovers in episodes that succeeded, with ``takeover_tail`` only the last
steps of each, as ``hitl finetune`` selects them from segment files) with the job's recipe
(``policy.finetune``: 50/50 batches with the pretraining data, steps growing with K) and evaluate it
autonomously through the controller on seeded episodes of the training object and of each unseen
object. Every point is independent and starts from the same pretrained weights; results are cached
per point under ``--cache``.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lab.assisted import AssistConfig, run_assisted
from policy.checkpoint import check_fits, load_policy, read_info
from policy.finetune import FinetuneConfig, TaskResult, evaluate_episodes, finetune_policy, pretraining_split
from storage import keys
from storage.paths import resolve
from storage.takeovers import SUCCESS, TakeoverSelection, TakeoverSet

FULL = "full-trajectory"
GRASP = "expert:grasp"
GRASP_WINDOW = (20, 13)  # expert:grasp keeps this many steps before the gripper first closes, and from it on
UNSEEN = ("lift-nut", "lift-hammer", "lift-hook")
HAND_BACKS = ("continuous", "budgeted", "operator")


@dataclass(frozen=True)
class FinetuneBenchConfig:
    policy: str = "policies/state/lift-cube"  # its takeover samples are state and action, no frames
    train_task: str = "lift-cube"
    unseen: tuple[str, ...] = UNSEEN
    sources: tuple[str, ...] = ("takeover:spread", "takeover:denoising", "takeover:random", FULL)
    counts: tuple[int, ...] = (20, 50, 100, 200)
    eval_episodes: int = 20
    eval_seed: int = 50_000
    collect_seed: int = 70_000
    collect_rounds: int = 6  # waves of episodes per unseen task while collecting, at most
    # the demo fleet's rules (configs/demo.toml): the operator keeps control while the signal wants help,
    # then `cooldown` policy steps before the robot may ask again. (With budgeted 4-step takeovers the
    # operator only ever corrects the approach: no takeover of 4 steps reaches the grasp.)
    hand_back: str = "continuous"  # or "budgeted", or "operator": continuous until the operator hands back, once held
    budget: int = 4
    cooldown: int = 10
    return_after: int = 1  # continuous: the operator hands back after this many steps the signal is calm
    # fine-tune on every stride-th step of each run of samples (each source alike); a policy with
    # observation and action horizons of 1 only (a subsampled run has no chunks of consecutive actions)
    stride: int = 1
    # each point this many times: repeat r > 0 draws its samples from the runs in another seeded order
    # and fine-tunes with seed + r (the spread says how much one point can be trusted)
    repeats: int = 1
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)

    def __post_init__(self) -> None:
        from policy.signals.registry import SIGNALS

        if self.hand_back not in HAND_BACKS:
            raise ValueError(f"hand_back must be one of {HAND_BACKS}, got {self.hand_back!r}")
        if self.return_after != 1 and self.hand_back != "continuous":
            raise ValueError(f"return_after applies to the continuous hand-back only, not to {self.hand_back!r}")

        for source in self.sources:
            kind, _, signal = source.partition(":")
            if source not in (FULL, GRASP) and not (kind == "takeover" and signal in SIGNALS):
                raise ValueError(
                    f"unknown source {source!r}: {FULL}, {GRASP} or takeover:SIGNAL with SIGNAL one of "
                    + ", ".join(SIGNALS)
                )
        for name in ("stride", "repeats"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if not self.counts or any(not (isinstance(k, int) and k >= 1) for k in self.counts):
            raise ValueError(f"counts must be integers >= 1, got {self.counts!r}")

    @classmethod
    def quick(cls, **kw) -> FinetuneBenchConfig:
        base = {"sources": ("takeover:spread", FULL), "counts": (50, 100), "eval_episodes": 10}
        return cls(**(base | kw))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["finetune"] = self.finetune.to_dict()
        return d

    def digest(self, *parts) -> str:
        """A cache key of this config and ``parts``. Recipe fields added later are left out at their
        defaults, so the points computed before they existed are still found."""
        d = self.to_dict()
        d.pop("repeats")  # a point's repeat is one of its parts
        d["finetune"] = {k: v for k, v in d["finetune"].items() if _LATER_DEFAULTS.get(k, ...) != v}
        doc = json.dumps([d, *parts], sort_keys=True, default=str)
        return hashlib.sha256(doc.encode()).hexdigest()[:16]

    def for_source(self, source: str | None) -> FinetuneBenchConfig:
        """This config as it bears on ``source`` (None: on the pretrained policy): the takeover selection
        only on takeover sources, so other points and their cache keys do not depend on it."""
        if source is not None and source.startswith("takeover:"):
            return self
        return replace(self, finetune=replace(self.finetune, successful_only=False, takeover_tail=None))

    def selection(self, source: str) -> TakeoverSelection:
        """The recipe's takeover selection for a takeover source; every step of the other sources."""
        return self.finetune.selection if source.startswith("takeover:") else TakeoverSelection()


_LATER_DEFAULTS = {"successful_only": False, "takeover_tail": None}  # FinetuneConfig fields newer than the cache


@dataclass
class Samples:
    """Per unseen task, the runs of consecutive (observation, action) pairs, in collection order, and
    per run whether its episode succeeded (a task missing from ``successful``: every run, as the
    demonstrations' episodes do)."""

    runs: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    successful: dict[str, list[bool]] = field(default_factory=dict)

    def save(self, path: Path) -> None:
        arrays = {}
        for t, runs in self.runs.items():
            arrays[f"{t}/obs"] = np.concatenate([o for o, _ in runs]) if runs else np.zeros((0, 0), np.float32)
            arrays[f"{t}/act"] = np.concatenate([a for _, a in runs]) if runs else np.zeros((0, 10), np.float32)
            arrays[f"{t}/len"] = np.array([len(o) for o, _ in runs], np.int64)
            if t in self.successful:
                arrays[f"{t}/successful"] = np.array(self.successful[t], bool)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> Samples:
        runs: dict[str, list] = {}
        successful: dict[str, list[bool]] = {}
        with np.load(path) as z:
            for t in dict.fromkeys(k.split("/")[0] for k in z.files):
                ends = np.cumsum(z[f"{t}/len"])
                starts = ends - z[f"{t}/len"]
                runs[t] = [(z[f"{t}/obs"][a:b], z[f"{t}/act"][a:b]) for a, b in zip(starts, ends, strict=True)]
                if f"{t}/successful" in z.files:
                    successful[t] = z[f"{t}/successful"].tolist()
        return cls(runs, successful)

    def shuffled(self, seed: int) -> Samples:
        """The same runs in a seeded random order per task (seed 0: as they are)."""
        if seed == 0:
            return self
        runs, successful = {}, {}
        for i, (task, task_runs) in enumerate(self.runs.items()):
            order = np.random.default_rng([seed, i]).permutation(len(task_runs))
            runs[task] = [task_runs[j] for j in order]
            if task in self.successful:
                successful[task] = [self.successful[task][j] for j in order]
        return Samples(runs, successful)

    def kept(self, task: str, selection: TakeoverSelection) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(whole length, observations, actions) of each of ``task``'s runs that ``selection`` keeps,
        cropped to its steps, in order; a run it leaves out as (whole length, None, None)."""
        flags = self.successful.get(task) or [True] * len(self.runs[task])
        out = []
        for (o, a), ok in zip(self.runs[task], flags, strict=True):
            if selection.why_excluded(SUCCESS if ok else "failure") is not None:
                out.append((len(o), None, None))
                continue
            keep = selection.steps(len(o))
            out.append((len(o), o[keep], a[keep]))
        return out

    def enough(self, need: int, selection: TakeoverSelection) -> bool:
        """Whether every task has ``need`` steps that ``selection`` keeps."""
        return all(sum(len(o) for _, o, _ in self.kept(t, selection) if o is not None) >= need for t in self.runs)

    def count(self) -> dict[str, int]:
        return {t: sum(len(o) for o, _ in r) for t, r in self.runs.items()}

    def gripper_closed_share(self) -> dict[str, float]:
        """Per task, the share of samples whose action closes the gripper: whether the data reaches grasps."""
        return {
            t: float(np.mean(np.concatenate([a[:, -1] for _, a in r]) > 0)) if r else 0.0 for t, r in self.runs.items()
        }

    def draw(self, k: int, stride: int = 1, selection: TakeoverSelection | None = None) -> tuple[TakeoverSet, int]:
        """The first ``k`` samples, ``k / len(tasks)`` from each task (the remainder to the first ones),
        whole runs in order, the last one cut (to its first steps; to its last ones with a ``selection``
        tail, which keeps the steps next to the hand-back); with ``stride`` s, every s-th step of each
        run (its steps 0, s, 2s, ...: the runs as recorded at 1/s of the control rate). Runs the
        ``selection`` leaves out are passed over. Also returns the steps recorded in every run drawn
        from or passed over: what the K samples cost the operator (or the expert)."""
        selection = selection or TakeoverSelection()
        tasks = list(self.runs)
        share = [k // len(tasks) + (1 if i < k % len(tasks) else 0) for i in range(len(tasks))]
        obs, act, ends, total, recorded = [], [], [], 0, 0
        for task, want in zip(tasks, share, strict=True):
            left = want
            for whole, o, a in self.kept(task, selection):
                if left <= 0:
                    break
                recorded += whole
                if o is None:
                    continue
                o, a = o[::stride], a[::stride]
                cut = slice(-left, None) if selection.tail is not None else slice(0, left)
                o, a = (o[cut], a[cut]) if len(o) > left else (o, a)
                obs.append(o)
                act.append(a)
                total += len(o)
                ends.append(total)
                left -= len(o)
            if left > 0:
                raise ValueError(f"only {want - left} samples of {task} collected, {want} wanted")
        obs_a, act_a = np.concatenate(obs), np.concatenate(act)
        data = TakeoverSet(obs_a, act_a, np.zeros((len(obs_a), 7), np.float32), np.array(ends, np.int64))
        return data, recorded


def grasp_window(obs: np.ndarray, act: np.ndarray, window: tuple[int, int] = GRASP_WINDOW):
    """The steps of one demonstration from ``window[0]`` before the first action that closes the gripper
    to ``window[1]`` from it on; the whole demonstration when it never closes."""
    closing = np.flatnonzero(act[:, -1] > 0)
    if not len(closing):
        return obs, act
    at = int(closing[0])
    cut = slice(max(0, at - window[0]), at + window[1])
    return obs[cut], act[cut]


def first_close_summary(episodes) -> dict | None:
    """Where the gripper was first told to close over ``episodes`` (the lift tasks' ``episode_info``):
    how many closed, and the median distance in the plane from the grasp point and from the body origin
    (m); None for a task that records neither."""
    infos = [e.info for e in episodes if "first_close_to_grasp_m" in e.info]
    if not infos:
        return None
    closed = [i for i in infos if i["first_close_to_grasp_m"] is not None]

    def median(key: str) -> float | None:
        return float(np.median([i[key] for i in closed])) if closed else None

    return {
        "episodes": len(infos),
        "closed": len(closed),
        "median_to_grasp_m": median("first_close_to_grasp_m"),
        "median_to_origin_m": median("first_close_to_origin_m"),
    }


def _signal_digest(policy_dir: str, source: str) -> str | None:
    """For ``takeover:SIGNAL``, a digest of the signal's saved config and calibration (takeovers collected
    with an older calibration are not reused); None for the other sources or an unsaved signal."""
    from policy.signals.registry import CONFIG, signal_dir

    kind, _, name = source.partition(":")
    path = signal_dir(policy_dir, name) / CONFIG if kind == "takeover" else None
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path is not None and path.is_file() else None


def _runs_from_episodes(episodes, seed: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[bool]]:
    """The operator's takeovers (runs of consecutive operator steps) in a seeded random order: the first
    K samples are then a draw of whole takeovers from all the episodes, wherever in them the signal asked
    (in the order a fleet records them, K samples from robots running side by side would all be their
    episodes' first steps). Also, per takeover, whether its episode succeeded."""
    runs, successful = [], []
    for ep in episodes:
        flags = np.asarray(ep.operator, bool)
        at = 0
        for start in np.flatnonzero(flags & ~np.r_[False, flags[:-1]]):
            n = int(np.argmin(np.r_[flags[start:], False]))  # length of this run of operator steps
            chunk = ep.takeover_pairs[at : at + n]
            at += n
            runs.append((np.stack([p[0] for p in chunk]), np.stack([p[1] for p in chunk])))
            successful.append(bool(ep.success))
    order = np.random.default_rng(seed).permutation(len(runs))
    return [runs[i] for i in order], [successful[i] for i in order]


def collect(
    policy, policy_dir: str, source: str, cfg: FinetuneBenchConfig, need: int, cache: Path, progress: bool
) -> Samples:
    """At least ``need`` samples per unseen task from ``source`` that the config's selection keeps (or
    as many as ``collect_rounds`` give); expert demonstrations are recorded once under ``cache``."""
    from policy.signals import load_signal
    from sim.demos import record_demos
    from storage.dataset import DatasetConfig, load_dataset

    runs: dict[str, list] = {}
    successful: dict[str, list[bool]] = {}
    selection = cfg.selection(source)
    for ti, task in enumerate(cfg.unseen):
        runs[task] = []
        for r in range(cfg.collect_rounds):
            seeds = list(range(cfg.collect_seed + 1000 * ti + 16 * r, cfg.collect_seed + 1000 * ti + 16 * (r + 1)))
            if source in (FULL, GRASP):
                folder = cache / "demos" / task / f"seed{seeds[0]}"
                if not any(folder.glob("*.mcap")):
                    record_demos(task, len(seeds), folder, seed=seeds[0], progress=progress)
                ds = load_dataset(folder, DatasetConfig(val_fraction=0.0))
                new = [(ds.obs[s:e], ds.actions[s:e]) for s, e in zip(ds.episode_starts, ds.episode_ends, strict=True)]
                if source == GRASP:
                    new = [grasp_window(o, a) for o, a in new]
            elif source.startswith("takeover:"):
                signal = load_signal(policy, policy_dir, source.split(":", 1)[1])
                by_operator = cfg.hand_back == "operator"
                assist = AssistConfig(
                    hand_back="continuous" if by_operator else cfg.hand_back,
                    budget=cfg.budget,
                    cooldown=cfg.cooldown,
                    return_after=None if by_operator else cfg.return_after,
                    operator_hands_back=by_operator,
                    n_envs=4,
                    seed=cfg.collect_seed,
                )
                episodes, _ = run_assisted(policy, task, seeds, signal, config=assist, progress=progress)
                new, flags = _runs_from_episodes(episodes, seeds[0])
                successful[task] = successful.get(task, []) + flags
            else:  # FinetuneBenchConfig refuses any other
                raise ValueError(f"unknown source {source!r}")
            runs[task] += new
            if Samples({task: runs[task]}, successful).enough(need, selection):
                break
    return Samples(runs, successful)


def run_bench(cfg: FinetuneBenchConfig, cache: str | Path = "runs/bench-finetune", progress: bool = True) -> dict:
    """Every (source, count) point, plus the pretrained policy's own success; JSON-ready."""
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    parent, info = load_policy(cfg.policy)
    for task in dict.fromkeys([cfg.train_task, *cfg.unseen]):
        check_fits(info, task, cfg.policy)
    if parent.config.cameras:
        raise ValueError(
            f"{cfg.policy} sees cameras: this benchmark's takeover samples hold the state and the action, not the "
            "frames; fine-tune a policy that sees through the service's job (docs/finetune.md)"
        )
    if cfg.stride > 1 and (parent.config.obs_horizon > 1 or parent.config.action_horizon > 1):
        raise ValueError(f"stride {cfg.stride} needs a policy with observation and action horizons of 1")
    pre_train = pretraining_split(parent, info, resolve(info["dataset"]["folder"])).train
    tasks = [cfg.train_task, *cfg.unseen]
    start = time.perf_counter()

    computed = []  # the cache keys computed by this run (the rest were read from the cache)

    def cached(key: str, compute):
        path = cache / f"{key}.json"
        if path.is_file():
            return json.loads(path.read_text())
        computed.append(key)
        value = compute()
        path.write_text(json.dumps(value) + "\n")
        return value

    def success(policy) -> dict:
        runs = evaluate_episodes(policy, tasks, cfg.eval_episodes, cfg.eval_seed, progress)
        return {
            t: TaskResult.from_episodes(t, eps, cfg.eval_seed).to_dict() | {"first_close": first_close_summary(eps)}
            for t, eps in runs.items()
        }

    base_key = "pretrained-" + cfg.for_source(None).digest("pretrained", tasks, cfg.eval_episodes, cfg.eval_seed)
    pretrained = cached(base_key, lambda: success(parent))
    need = -(-max(cfg.counts) // len(cfg.unseen)) * cfg.stride
    points, skipped, collected = [], {}, {}
    todo = [(s, k, r) for s in cfg.sources for k in cfg.counts for r in range(cfg.repeats)]
    bar = tqdm(todo, desc="bench finetune", unit="point", disable=not progress)
    samples: dict[str, Samples] = {}
    for source, k, rep in bar:
        bar.set_postfix(source=source, k=k, repeat=rep)
        if source in skipped:
            continue
        if source not in samples:
            what = [cfg.policy, cfg.unseen, cfg.collect_seed, cfg.collect_rounds, cfg.hand_back, cfg.budget]
            what += [cfg.cooldown, source, need] + ([cfg.return_after] if cfg.return_after != 1 else [])
            what += [GRASP_WINDOW] if source == GRASP else []
            what += [_signal_digest(cfg.policy, source)]
            selection = cfg.selection(source)
            what += ["success flags"] if selection.successful_only else []  # files from before them have none
            digest = hashlib.sha256(json.dumps(what, default=str).encode()).hexdigest()[:16]
            stored = cache / f"samples-{source.replace(':', '_')}-{digest}.npz"
            try:
                loaded = Samples.load(stored) if stored.is_file() else None
                # collection is seeded: a longer one (for a selection that keeps less) starts the same
                samples[source] = (
                    loaded
                    if loaded is not None and loaded.enough(need, selection)
                    else collect(parent, cfg.policy, source, cfg, need, cache, progress)
                )
            except Exception as exc:  # noqa: BLE001 - a signal that is not trained next to this policy
                skipped[source] = f"{type(exc).__name__}: {exc}"
                continue
            samples[source].save(stored)
            collected[source] = {
                "samples": samples[source].count(),
                "takeovers": {t: len(r) for t, r in samples[source].runs.items()},
                "gripper_closed_share": samples[source].gripper_closed_share(),
            } | (
                {"in_successful_episodes": {t: sum(f) for t, f in flags.items()}}
                if (flags := samples[source].successful)
                else {}
            )
        key = f"point-{source.replace(':', '_')}-{k}-" + cfg.for_source(source).digest(
            source, k, tasks, *([rep] if rep else [])
        )
        try:
            data, steps = samples[source].shuffled(rep).draw(k, cfg.stride, cfg.selection(source))
            recorded, error = {"recorded_steps": steps}, None
        except ValueError as exc:
            data, recorded, error = None, {}, str(exc)

        def compute(data=data, error=error, rep=rep) -> dict:
            if data is None:
                return {"error": error}
            arrays = data.arrays(parent.config.obs_horizon, parent.config.action_horizon)
            recipe = replace(cfg.finetune, seed=cfg.finetune.seed + rep)
            child, history = finetune_policy(parent, arrays, pre_train, recipe, progress=False)
            return {
                "steps": history["steps"],
                "obs_dims_widened": history["obs_dims_widened"],
                "seconds": round(history["seconds"], 1),
                "success": success(child),
            }

        result = cached(key, compute)
        points.append({"source": source, "samples": k, "repeat": rep, **recorded, **result})
    bar.close()
    return {
        "benchmark": "finetune",
        "policy": str(cfg.policy),
        "trained_on": info.get("task"),
        "config": cfg.to_dict(),
        "pretrained": pretrained,
        "points": points,
        "collected": collected,
        "skipped_sources": skipped,
        "seconds": round(time.perf_counter() - start, 1),
        "computed_in_this_run": len(computed),
        "read_from_cache": len(points) + 1 - len(computed),
        "pretraining": {"folder": info["dataset"]["folder"], "samples": int(len(pre_train[keys.OBS]))},
        "policy_info": {"command": read_info(cfg.policy).get("command")},
    }

"""Training loop: AdamW, warm-up + cosine learning rate, EMA weights, seeded.

A plain function with ``try/finally`` cleanup; the EMA copy of the weights is
what gets returned and saved, as in Chi et al.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from storage import keys


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 20_000
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    ema_decay: float = 0.999
    seed: int = 0
    val_every: int = 1000
    threads: int | None = None
    symmetry_augment: bool = False  # each sample's observation turned into a random identical pose
    # m: each sample sees its object up to this far from where it is, along each axis across the table (x, y;
    # object-frame policies only: ``policy.frames.ObjectFrame.shifted``); 0: off
    origin_jitter: float = 0.0
    # m: each sample sees its end effector and its targets up to this far higher or lower against the object
    # (object-frame policies only: ``policy.frames.ObjectFrame.raised``); 0: off
    height_jitter: float = 0.0

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "val_every"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"lr must be a positive number, got {self.lr!r}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay!r}")
        for name in ("origin_jitter", "height_jitter"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and not isinstance(v, bool) and 0 <= v < math.inf):
                raise ValueError(f"{name} must be a number >= 0, got {v!r}")
        if not (isinstance(self.warmup_steps, int) and self.warmup_steps >= 0):
            raise ValueError(f"warmup_steps must be an integer >= 0, got {self.warmup_steps!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TrainState:
    """Everything needed to continue a training run exactly where it stopped: the next step, the
    weights, the EMA weights, the optimizer's moments, the sampling generator and the loss history.
    Saved as ``train_state.safetensors`` + ``train_state.json`` (no pickle) in a folder per save."""

    step: int
    model: dict[str, torch.Tensor]
    ema: dict[str, torch.Tensor]
    optimizer: dict
    generator: torch.Tensor
    running: float
    history: dict = field(default_factory=dict)

    TENSORS = "train_state.safetensors"
    META = "train_state.json"
    LATEST = "latest"  # names the complete state folder to resume from

    def save(self, folder: str | Path) -> Path:
        """Writes ``folder/step-<N>/`` (both files), then points ``folder/latest`` at it with one atomic
        rename: a crash at any moment leaves the previous complete state to resume from."""
        folder = Path(folder)
        target = folder / f"step-{self.step:08d}"
        target.mkdir(parents=True, exist_ok=True)
        tensors = {f"model.{k}": v for k, v in self.model.items()}
        tensors |= {f"ema.{k}": v for k, v in self.ema.items()}
        tensors["generator"] = self.generator
        for idx, moments in self.optimizer["state"].items():
            for key, value in moments.items():
                tensors[f"opt.{idx}.{key}"] = torch.as_tensor(value)
        tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
        meta = {
            "step": self.step,
            "running": self.running,
            "history": self.history,
            "param_groups": self.optimizer["param_groups"],
        }
        save_file(tensors, str(target / self.TENSORS))
        (target / self.META).write_text(json.dumps(meta) + "\n")
        pointer = folder / (self.LATEST + ".tmp")
        pointer.write_text(target.name + "\n")
        pointer.replace(folder / self.LATEST)
        for old in folder.glob("step-*"):
            if old != target:
                shutil.rmtree(old, ignore_errors=True)
        return target

    @classmethod
    def _latest(cls, folder: str | Path) -> Path | None:
        pointer = Path(folder) / cls.LATEST
        if not pointer.is_file():
            return None
        target = Path(folder) / pointer.read_text().strip()
        return target if (target / cls.TENSORS).is_file() and (target / cls.META).is_file() else None

    @classmethod
    def exists(cls, folder: str | Path) -> bool:
        return cls._latest(folder) is not None

    @classmethod
    def load(cls, folder: str | Path) -> TrainState:
        """The latest complete state saved under ``folder``."""
        target = cls._latest(folder)
        if target is None:
            raise FileNotFoundError(f"no complete training state in {folder}")
        tensors = load_file(str(target / cls.TENSORS))
        meta = json.loads((target / cls.META).read_text())
        model = {k.removeprefix("model."): v for k, v in tensors.items() if k.startswith("model.")}
        ema = {k.removeprefix("ema."): v for k, v in tensors.items() if k.startswith("ema.")}
        state: dict[int, dict] = {}
        for k, v in tensors.items():
            if k.startswith("opt."):
                _, idx, key = k.split(".", 2)
                state.setdefault(int(idx), {})[key] = v
        optimizer = {"state": state, "param_groups": meta["param_groups"]}
        return cls(meta["step"], model, ema, optimizer, tensors["generator"], meta["running"], meta["history"])


def _lr_factor(step: int, cfg: TrainConfig) -> float:
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    progress = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


@torch.no_grad()
def _val_loss(policy: DiffusionPolicy, val: dict[str, torch.Tensor], seed: int, batch: int = 1024) -> float:
    g = torch.Generator().manual_seed(seed)
    n = val[keys.OBS].shape[0]
    losses = []
    for i in range(0, n, batch):
        part = {k: v[i : i + batch] for k, v in val.items()}
        losses.append(float(policy.compute_loss(part, generator=g)) * part[keys.OBS].shape[0])
    return sum(losses) / max(n, 1)


def train_policy(
    policy: DiffusionPolicy,
    train: dict[str, np.ndarray],
    val: dict[str, np.ndarray] | None,
    cfg: TrainConfig,
    progress: bool = True,
    symmetry: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    symmetry_order: int = 1,
    sampler: Callable[[int, torch.Generator], torch.Tensor] | None = None,
    resume: TrainState | None = None,
    checkpoint: Callable[[TrainState], None] | None = None,
    checkpoint_every: int = 100,
) -> tuple[DiffusionPolicy, dict]:
    """Trains ``policy`` (normalizers must already be fitted) on {OBS, ACTION} arrays.

    With ``cfg.symmetry_augment``, ``symmetry(obs, k)`` (a task's ``symmetric_observation``) turns
    each sampled observation history into one of its ``symmetry_order`` identical poses, drawn
    at random; the action is unchanged, since the scene is physically the same.

    ``sampler(batch, generator)`` draws each mini-batch's row indices (default: uniform over all rows);
    fine-tuning passes a ``policy.mixing.MixedSampler`` over takeover and pretraining rows concatenated.

    With ``cfg.origin_jitter`` (an object-frame policy's), each sample sees its object shifted across the
    table by a uniform random offset of up to that many metres along x and y (``ObjectFrame.shifted``); the
    actions are unchanged, so they are expressed relative to the shifted object. The height is left alone:
    the object's height above the table is what tells a lifted object from one at rest. With
    ``cfg.height_jitter``, each sample's end effector and actions are seen up to that much higher or lower
    against the object instead (``ObjectFrame.raised``).

    ``checkpoint(state)`` receives a ``TrainState`` every ``checkpoint_every`` steps (and after the
    last); ``resume`` continues from one: the result is the same as an uninterrupted run's.

    Returns (EMA policy, history with loss curves and timing).
    """
    threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    data = {k: torch.as_tensor(v) for k, v in train.items()}
    val_t = {k: torch.as_tensor(v) for k, v in val.items()} if val and len(val[keys.OBS]) else None
    n = data[keys.OBS].shape[0]
    g = torch.Generator().manual_seed(cfg.seed)
    if cfg.symmetry_augment and (symmetry is None or symmetry_order < 2):
        raise ValueError("symmetry_augment needs a task whose scene has a symmetry (symmetry_order >= 2)")
    if (cfg.origin_jitter or cfg.height_jitter) and policy.frame is None:
        raise ValueError("origin_jitter and height_jitter need an object-frame policy (hitl train --frame object)")
    ema = copy.deepcopy(policy).eval()
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    history: dict = {"step": [], "train_loss": [], "val_step": [], "val_loss": []}
    running, first = 0.0, 0
    if resume is not None:
        policy.load_state_dict(resume.model)
        ema.load_state_dict(resume.ema)
        opt.load_state_dict(resume.optimizer)
        g.set_state(resume.generator)
        running, first, history = resume.running, resume.step, copy.deepcopy(resume.history)

    def snapshot(next_step: int) -> TrainState:
        return TrainState(
            next_step,
            {k: v.detach().clone() for k, v in policy.state_dict().items()},
            {k: v.detach().clone() for k, v in ema.state_dict().items()},
            copy.deepcopy(opt.state_dict()),
            g.get_state(),
            running,
            copy.deepcopy(history),
        )

    bar = tqdm(total=cfg.steps, initial=first, desc="train", disable=not progress, unit="step", smoothing=0.05)
    start = time.perf_counter()
    try:
        policy.train()
        for step in range(first, cfg.steps):
            for group in opt.param_groups:
                group["lr"] = cfg.lr * _lr_factor(step, cfg)
            draw = sampler or (lambda size, gen: torch.randint(0, n, (size,), generator=gen))
            idx = draw(cfg.batch_size, g)
            batch = {k: v[idx] for k, v in data.items()}
            if cfg.symmetry_augment:
                turn = torch.randint(0, symmetry_order, (cfg.batch_size, 1), generator=g).numpy()
                batch[keys.OBS] = torch.as_tensor(symmetry(batch[keys.OBS].numpy(), turn), dtype=torch.float32)
            if cfg.origin_jitter:
                offset = (torch.rand(cfg.batch_size, 3, generator=g) * 2 - 1) * cfg.origin_jitter
                offset[:, 2] = 0.0  # across the table only: the object's height tells a lifted object from one at rest
                batch[keys.OBS] = policy.frame.shifted(batch[keys.OBS], offset)
            if cfg.height_jitter:
                height = (torch.rand(cfg.batch_size, generator=g) * 2 - 1) * cfg.height_jitter
                batch[keys.OBS], batch[keys.ACTION] = policy.frame.raised(batch[keys.OBS], batch[keys.ACTION], height)
            loss = policy.compute_loss(batch, generator=g)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"training loss became {float(loss)} at step {step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():
                decay = min(cfg.ema_decay, (1 + step) / (10 + step))
                for pe, p in zip(ema.parameters(), policy.parameters(), strict=True):
                    pe.lerp_(p, 1 - decay)
            value = float(loss.detach())
            running = 0.98 * running + 0.02 * value if step else value
            if step % 50 == 0 or step == cfg.steps - 1:
                history["step"].append(step)
                history["train_loss"].append(running)
                bar.set_postfix(loss=f"{running:.4f}")
            if val_t is not None and ((step + 1) % cfg.val_every == 0 or step == cfg.steps - 1):
                history["val_step"].append(step + 1)
                history["val_loss"].append(_val_loss(ema, val_t, cfg.seed))
                bar.set_postfix(loss=f"{running:.4f}", val=f"{history['val_loss'][-1]:.4f}")
            bar.update(1)
            if checkpoint is not None and ((step + 1) % checkpoint_every == 0 or step == cfg.steps - 1):
                checkpoint(snapshot(step + 1))
    finally:
        bar.close()
        policy.eval()
        torch.set_num_threads(threads)
    history["seconds"] = time.perf_counter() - start
    history["samples"] = n
    return ema, history

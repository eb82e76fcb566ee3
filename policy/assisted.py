"""Assisted rollouts: a driver signal decides when the simulated operator (the task's scripted
expert) takes over; every other signal runs in shadow on the same trajectory.

At each takeover the operator picks up where the scene stands (``Expert.resume``: an object
already held is lifted, not dropped to start over). Per step and robot: the policy samples a
chunk (robots under teleop too: that is the robot's would-be action for switch-back rules and
for the signals); every signal scores every robot; the driver's ``wants_help`` (with the teleop
flags) starts or ends takeovers.

Modes, as in the paper: ``budgeted`` gives the operator ``budget`` steps per assistance event;
``continuous`` keeps the operator in control until the driver no longer wants help (for
``thrifty`` this is its switch-back rule; for the others the score back under the threshold).
On hand-back the policy restarts from the current pose with a fresh observation history.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import AssistanceSignal, SignalInput, TriggerState
from sim.env import Task
from sim.registry import make_expert, make_task

MODES = ("budgeted", "continuous")


@dataclass(frozen=True)
class AssistConfig:
    mode: str = "budgeted"
    budget: int = 4  # operator steps per assistance event (budgeted mode)
    n_envs: int = 4
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        for name in ("budget", "n_envs"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")


@dataclass
class AssistedEpisode:
    task: str
    seed: int
    driver: str
    success: bool = False
    steps: int = 0
    operator: list[bool] = field(default_factory=list)  # who executed each step
    policy_in_control: list[bool] = field(default_factory=list)  # before each step's decision
    events: int = 0  # assistance requests by the driver
    scores: dict[str, list[float]] = field(default_factory=dict)  # every signal, every step
    wants: dict[str, list[bool]] = field(default_factory=dict)

    @property
    def assisted_steps(self) -> int:
        return int(sum(self.operator))

    def summary(self) -> dict:
        return {
            "seed": self.seed,
            "success": self.success,
            "steps": self.steps,
            "assisted_steps": self.assisted_steps,
            "events": self.events,
        }


def _run_wave(
    policy: DiffusionPolicy,
    tasks: list[Task],
    seeds: list[int],
    first_id: int,
    driver: AssistanceSignal,
    shadow: dict[str, AssistanceSignal],
    cfg: AssistConfig,
    bar: tqdm,
) -> list[AssistedEpisode]:
    n, h = len(seeds), policy.config.obs_horizon
    ids = np.arange(first_id, first_id + n)
    signals = {driver.name: driver, **shadow}
    for s in signals.values():
        s.reset(ids)
    experts = [make_expert(t.name) for t in tasks]
    obs = [t.reset(s) for t, s in zip(tasks, seeds, strict=True)]
    histories = [deque([torch.as_tensor(o, dtype=torch.float32)] * h, maxlen=h) for o in obs]
    queues: list[deque] = [deque() for _ in range(n)]
    teleop = np.zeros(n, dtype=bool)
    budget = np.zeros(n, dtype=int)
    episodes = [
        AssistedEpisode(t.name, s, driver.name, scores={k: [] for k in signals}, wants={k: [] for k in signals})
        for t, s in zip(tasks, seeds, strict=True)
    ]
    active = np.ones(n, dtype=bool)
    g = torch.Generator().manual_seed(cfg.seed + first_id)
    while active.any():
        live = np.flatnonzero(active)
        hist = torch.stack([torch.stack(list(histories[i])) for i in live])
        chunks = policy.predict_action_chunk(hist, generator=g)  # (L, C, 10): also the would-be action under teleop
        current = np.stack([tasks[i].hold_action() for i in live]).astype(np.float32)
        operator = np.full((len(live), 10), np.nan, dtype=np.float32)
        for j, i in enumerate(live):
            if teleop[i]:
                operator[j] = tasks[i].teleop(experts[i].act(tasks[i])).action
        batch = SignalInput(hist, current, ids[live], action=chunks, operator_action=torch.as_tensor(operator))
        state = TriggerState(ids[live], teleop[live].copy())
        decisions = {}
        for name, signal in signals.items():
            scores = signal.score(batch)
            decisions[name] = signal.wants_help(scores, state)
            for j, i in enumerate(live):
                episodes[i].scores[name].append(float(scores.value[j]))
                episodes[i].wants[name].append(bool(decisions[name][j]))
        ask = decisions[driver.name]
        for j, i in enumerate(live):
            episodes[i].policy_in_control.append(not teleop[i])
            if not teleop[i] and ask[j]:  # the robot holds and asks; the operator answers this step
                teleop[i], budget[i] = True, cfg.budget
                episodes[i].events += 1
                experts[i].resume(tasks[i], np.random.default_rng([seeds[i], episodes[i].events]))
                operator[j] = tasks[i].teleop(experts[i].act(tasks[i])).action
            elif teleop[i] and cfg.mode == "continuous" and not ask[j]:
                teleop[i] = False
                _hand_back(histories[i], queues[i], obs[i])
        for j, i in enumerate(live):
            if teleop[i]:
                action = operator[j].astype(np.float64)
            else:
                if not queues[i]:
                    queues[i].extend(chunks[j, : policy.config.n_action_steps].numpy())
                action = queues[i].popleft().astype(np.float64)
            result = tasks[i].step(action)
            ep = episodes[i]
            ep.operator.append(bool(teleop[i]))
            ep.steps = result.t
            obs[i] = result.obs
            histories[i].append(torch.as_tensor(result.obs, dtype=torch.float32))
            if teleop[i] and cfg.mode == "budgeted":
                budget[i] -= 1
                if budget[i] == 0:
                    teleop[i] = False
                    _hand_back(histories[i], queues[i], obs[i])
            if result.success or result.done:
                ep.success = bool(result.success)
                active[i] = False
                bar.update(1)
    return episodes


def _hand_back(history: deque, queue: deque, obs: np.ndarray) -> None:
    """The policy restarts from the current pose with a fresh observation history."""
    queue.clear()
    history.extend([torch.as_tensor(obs, dtype=torch.float32)] * history.maxlen)


def run_assisted(
    policy: DiffusionPolicy,
    task_name: str,
    seeds: list[int],
    driver: AssistanceSignal,
    shadow: dict[str, AssistanceSignal] | None = None,
    config: AssistConfig | None = None,
    progress: bool = True,
) -> tuple[list[AssistedEpisode], dict]:
    """One assisted episode per seed, in waves of ``n_envs`` robots stepping in lockstep."""
    cfg = config or AssistConfig()
    shadow = {k: v for k, v in (shadow or {}).items() if k != driver.name}
    tasks = [make_task(task_name) for _ in range(min(cfg.n_envs, len(seeds)))]
    if tasks[0].obs_spec.dim != policy.config.obs_dim:
        raise ValueError(
            f"policy expects {policy.config.obs_dim}-dim observations, task {task_name} gives {tasks[0].obs_spec.dim}"
        )
    episodes: list[AssistedEpisode] = []
    start = time.perf_counter()
    bar = tqdm(total=len(seeds), desc=f"assisted {task_name} ({driver.name})", disable=not progress, unit="ep")
    try:
        with torch.no_grad():
            for w in range(0, len(seeds), len(tasks)):
                wave = seeds[w : w + len(tasks)]
                episodes += _run_wave(policy, tasks[: len(wave)], wave, w, driver, shadow, cfg, bar)
    finally:
        bar.close()
        for t in tasks:
            t.close()
    return episodes, {"seconds": time.perf_counter() - start}


def summarize_assisted(episodes: list[AssistedEpisode]) -> dict:
    """Success, assisted steps and events per episode, and each signal's help rate on the steps where
    the policy was in control when the decision was taken (the rate to match a ``random`` reference to)."""
    auto = np.concatenate([np.asarray(e.policy_in_control, dtype=bool) for e in episodes])
    out = {
        "episodes": len(episodes),
        "driver": episodes[0].driver if episodes else None,
        "success_rate": float(np.mean([e.success for e in episodes])) if episodes else 0.0,
        "assisted_steps_per_episode": float(np.mean([e.assisted_steps for e in episodes])) if episodes else 0.0,
        "events_per_episode": float(np.mean([e.events for e in episodes])) if episodes else 0.0,
        "steps_per_episode": float(np.mean([e.steps for e in episodes])) if episodes else 0.0,
        "help_rate": {},
    }
    for name in episodes[0].wants if episodes else []:
        wants = np.concatenate([np.asarray(e.wants[name], dtype=bool) for e in episodes])
        out["help_rate"][name] = float(wants[auto].mean()) if auto.any() else None
    return out

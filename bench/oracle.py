"""The oracle: asks at the moments the task's privileged state marks, to measure how few operator steps
any asking signal could need on a policy and task (``bench.floor``, ``hitl bench floor``).

It is a measuring instrument, not an asking signal: it reads the simulator's state (the object's grasp
point, the hidden red cup, the intended drawer), which no signal the fleet serves can see, and it is not
in the signal registry. It runs through the one ``Controller`` like any signal, so its requests follow
the paper's protocol exactly (a hold step, then ``budget`` operator steps, then the policy; still in its
window, it asks again at once).

Each task family has windows, the phases where an operator's steps can change the outcome:

- ``grasp`` (the lift tasks): the object is not held and the end effector is within ``reach`` metres of
  its grasp point (where the policy stops short of an unseen object);
- ``insertion`` (cup-stack): the green cup is carried and its centre is within ``reach`` metres of the red
  cup's across the table (at 0.15 m: while the red cup is hidden);
- ``early`` (open-drawer): the policy's first ``reach`` steps, until the intended handle is held (the
  choice of drawer);
- ``astray`` (open-drawer): the intended handle is not held and the gripper is nearer, across the table,
  to another drawer's handle than to the intended one's by more than ``reach`` metres.

``requests`` caps the requests per episode (how long the oracle helps; None: while the window lasts).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    PerRobot,
    Scores,
    SignalConfig,
    SignalInput,
    TriggerState,
)
from sim.env import Task
from sim.experts import AT_GRASP, GRIPPED, CupStackExpert, LiftExpert, OpenDrawerExpert
from sim.registry import make_expert

WINDOWS: dict[type, tuple[str, ...]] = {
    LiftExpert: ("grasp",),
    CupStackExpert: ("insertion",),
    OpenDrawerExpert: ("early", "astray"),
}


def task_windows(task_name: str) -> tuple[str, ...]:
    """The oracle's windows for a registered task (its family's, by the task's scripted expert)."""
    return WINDOWS[type(make_expert(task_name))]


@dataclass(frozen=True)
class OracleConfig(SignalConfig):
    """window: one of the task's ``WINDOWS``; reach: its size (metres, or steps for ``early``);
    requests: the most requests per episode (None: no cap)."""

    window: str = "grasp"
    reach: float = 0.1
    requests: int | None = None

    def __post_init__(self) -> None:
        if self.window not in {w for ws in WINDOWS.values() for w in ws}:
            raise ValueError(f"unknown oracle window {self.window!r}")
        if not (isinstance(self.reach, int | float) and not isinstance(self.reach, bool) and self.reach >= 0):
            raise ValueError(f"reach must be a number >= 0, got {self.reach!r}")
        if self.requests is not None and not (
            isinstance(self.requests, int) and not isinstance(self.requests, bool) and self.requests >= 1
        ):
            raise ValueError(f"requests must be None or an integer >= 1, got {self.requests!r}")

    @property
    def label(self) -> str:
        cap = "no cap" if self.requests is None else f"≤ {self.requests} requests"
        unit = " steps" if self.window == "early" else " m"
        return f"{self.window} {self.reach:g}{unit}, {cap}"


def in_window(window: str, reach: float, scene: Task, policy_steps: int) -> bool:
    """Whether ``scene`` (a live task: ``privileged``, ``ee_pose``, ``gripper_opening``) is in the window."""
    s = scene.privileged()
    pos = scene.ee_pose()[0]
    if window == "grasp":
        return not LiftExpert().holding(scene) and float(np.linalg.norm(pos - s["grasp_point"])) < reach
    if window == "insertion":
        apart = float(np.linalg.norm(np.asarray(s["green_pos"])[:2] - np.asarray(s["red_pos"])[:2]))
        return CupStackExpert().holding(scene) and apart < reach
    handles = np.asarray(s["handles"])
    intended = int(s["intended"])
    held = scene.gripper_opening() < GRIPPED and float(np.linalg.norm(pos - handles[intended])) < AT_GRASP
    if held:
        return False
    if window == "early":
        return policy_steps < reach
    across = np.linalg.norm(handles[:, :2] - pos[:2], axis=1)
    others = np.delete(across, intended)
    return bool(across[intended] > others.min() + reach)


class Oracle(AssistanceSignal):
    """Asks while its robot's scene is in the configured window (``in_window``), up to ``requests``
    times per episode. ``watch`` gives it each robot's live task at the episode's start (the
    ``on_reset`` hook of ``lab.assisted.run_assisted``); a robot it was not given never asks."""

    name = "oracle"
    Config = OracleConfig

    def __init__(self, policy: DiffusionPolicy, config: OracleConfig | None = None) -> None:
        super().__init__(policy, config)
        self._scenes: dict[int, Task] = {}
        self._steps = PerRobot(int)  # policy steps scored so far this episode
        self._asked = PerRobot(int)  # requests so far this episode
        self.calibration = self._calibrate(None, False)

    def watch(self, robot_id: int, scene: Task) -> None:
        self._scenes[int(robot_id)] = scene
        self.reset([robot_id])

    def reset(self, robot_ids=None) -> None:
        ids = self._ids_for(robot_ids)
        self._steps.reset(ids)
        self._asked.reset(ids)

    def score(self, batch: SignalInput) -> Scores:
        cfg = self.config
        out = np.zeros(len(batch.robot_ids))
        for j, rid in enumerate(int(r) for r in batch.robot_ids):
            scene = self._scenes.get(rid)
            capped = cfg.requests is not None and self._asked.get(rid) >= cfg.requests
            if scene is not None and not capped and in_window(cfg.window, cfg.reach, scene, self._steps.get(rid)):
                out[j] = 1.0
        return Scores(out)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        out = (np.asarray(scores.value) > self.threshold) & ~np.asarray(state.teleop, dtype=bool)
        for j, rid in enumerate(int(r) for r in state.robot_ids):
            if not state.teleop[j]:
                self._steps.set(rid, self._steps.get(rid) + 1)
                self._asked.set(rid, self._asked.get(rid) + int(out[j]))
        return out

    def _calibrate(self, data: CalibrationData | None, progress: bool) -> dict:
        return {"threshold": 0.5, "quantile": None, "samples": 0, "source": f"oracle: {self.config.label}"}


def oracle_from(policy: DiffusionPolicy, settings: Mapping[str, object]) -> Oracle:
    return Oracle(policy, OracleConfig(**dict(settings)))

"""The ``AssistanceSignal`` interface: when should a robot ask a human for help?

A signal scores a batch of robots at one control step (``score``), decides from
those scores whether each robot wants help (``wants_help``; any trigger rule,
such as patience windows, cumulative sums or switch-back conditions, lives in
the signal, keyed by robot id), forgets robots at episode boundaries
(``reset``) and sets its threshold from data (``calibrate``).

Actions and observations are raw (world frame) at this interface; signals that
work in the policy's normalized action space normalize inside.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np
import torch

from policy.diffusion_policy import DiffusionPolicy

# the score part in which an asking signal says whether the policy, scored in shadow on an operator's step,
# agrees with it (1 / 0; NaN where no operator drives the robot); the robot's control state keeps it
AGREES = "agrees"


class SignalError(ValueError):
    """A signal cannot be built, calibrated or loaded as asked; the message says why."""


@dataclass
class SignalInput:
    """One control step of B robots.

    obs: (B, H, obs_dim) raw observation history;
    current: (B, 10) raw action that holds the current end-effector pose and gripper command;
    robot_ids: (B,) ids that key per-robot trigger state;
    action: (B, C, 10) raw chunk the policy sampled for this step, or None (the signal samples);
    operator_action: (B, 10) raw operator action, NaN rows for robots not under teleop, or None.
    """

    obs: torch.Tensor
    current: torch.Tensor
    robot_ids: np.ndarray
    action: torch.Tensor | None = None
    operator_action: torch.Tensor | None = None

    def __post_init__(self) -> None:
        self.obs = torch.as_tensor(self.obs, dtype=torch.float32)
        self.current = torch.as_tensor(self.current, dtype=torch.float32)
        self.robot_ids = np.asarray(self.robot_ids, dtype=np.int64)
        b = self.obs.shape[0]
        if self.obs.dim() != 3:
            raise ValueError(f"obs must have shape (B, H, obs_dim), got {tuple(self.obs.shape)}")
        if self.current.shape != (b, 10):
            raise ValueError(f"current must have shape ({b}, 10), got {tuple(self.current.shape)}")
        if self.robot_ids.shape != (b,):
            raise ValueError(f"robot_ids must have shape ({b},), got {self.robot_ids.shape}")
        if self.action is not None:
            self.action = torch.as_tensor(self.action, dtype=torch.float32)
            if self.action.dim() != 3 or self.action.shape[0] != b:
                raise ValueError(f"action must have shape ({b}, C, 10), got {tuple(self.action.shape)}")
        if self.operator_action is not None:
            self.operator_action = torch.as_tensor(self.operator_action, dtype=torch.float32)
            if self.operator_action.shape != (b, 10):
                raise ValueError(f"operator_action must have shape ({b}, 10), got {tuple(self.operator_action.shape)}")

    def __len__(self) -> int:
        return self.obs.shape[0]


@dataclass
class Scores:
    """value: (B,) the score the threshold applies to; parts: named (B,) components; detail: e.g. the
    denoising field for the console."""

    value: np.ndarray
    parts: dict[str, np.ndarray] = field(default_factory=dict)
    detail: object | None = None


@dataclass
class TriggerState:
    """What the trigger rule may know beyond the scores, per robot: its id, whether an operator drives it,
    and the takeover facts its control state keeps (``policy.hitl_state.RobotControl``), so that no
    signal keeps a copy of a robot's mode. engaged: the asking signal wanted help and no operator step
    has settled it since; agreed: 1 / 0 where the policy agreed / disagreed with the operator's last step
    (NaN: no operator step since the robot's last policy step); after_takeover: an operator drove the
    robot since its last policy step. Left out, a robot is autonomous with no takeover behind it."""

    robot_ids: np.ndarray
    teleop: np.ndarray | None = None  # (B,) bool
    engaged: np.ndarray | None = None  # (B,) bool
    agreed: np.ndarray | None = None  # (B,) float
    after_takeover: np.ndarray | None = None  # (B,) bool

    def __post_init__(self) -> None:
        ids = self.robot_ids
        self.robot_ids = np.asarray(ids if isinstance(ids, np.ndarray) else list(ids), dtype=np.int64)
        b = len(self.robot_ids)
        self.teleop = np.zeros(b, bool) if self.teleop is None else np.asarray(self.teleop, dtype=bool)
        self.engaged = np.zeros(b, bool) if self.engaged is None else np.asarray(self.engaged, dtype=bool)
        self.agreed = np.full(b, np.nan) if self.agreed is None else np.asarray(self.agreed, dtype=np.float64)
        self.after_takeover = (
            np.zeros(b, bool) if self.after_takeover is None else np.asarray(self.after_takeover, dtype=bool)
        )
        for name in ("teleop", "engaged", "agreed", "after_takeover"):
            if getattr(self, name).shape != (b,):
                raise ValueError(f"TriggerState.{name} must have shape ({b},), got {getattr(self, name).shape}")


@dataclass
class StepSet:
    """Recorded steps for calibration and auxiliary training (raw units).

    obs: (M, H, obs_dim); action: (M, C, 10) what was done (demonstrated or executed);
    current: (M, 10) the action holding the pose at that step; episode: (M,) episode index;
    t: (M,) step within the episode; last: (M,) the episode's final step; success: (M,) the
    episode ended in success; names: episode names.
    """

    obs: np.ndarray
    action: np.ndarray
    current: np.ndarray
    episode: np.ndarray
    t: np.ndarray
    last: np.ndarray
    success: np.ndarray
    names: list[str]

    def __len__(self) -> int:
        return len(self.obs)

    def take(self, rows: np.ndarray) -> StepSet:
        return StepSet(
            self.obs[rows],
            self.action[rows],
            self.current[rows],
            self.episode[rows],
            self.t[rows],
            self.last[rows],
            self.success[rows],
            self.names,
        )

    def episodes(self) -> list[np.ndarray]:
        """Row indices of each episode, in step order."""
        out = []
        for e in np.unique(self.episode):
            rows = np.flatnonzero(self.episode == e)
            out.append(rows[np.argsort(self.t[rows])])
        return out


@dataclass
class CalibrationData:
    """train / val: demonstration steps split by episode as the policy was trained;
    rollouts: the policy's own autonomous rollouts (for signals that need them)."""

    train: StepSet
    val: StepSet
    rollouts: StepSet | None = None


def quantile_record(values: np.ndarray, quantile: float, source: str) -> dict:
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0:
        raise SignalError(f"no calibration values from {source}")
    if not np.isfinite(values).all():
        raise SignalError(f"{int((~np.isfinite(values)).sum())} non-finite calibration values from {source}")
    return {
        "threshold": float(np.quantile(values, quantile)),
        "quantile": quantile,
        "samples": int(len(values)),
        "source": source,
        "stats": {"mean": float(values.mean()), "median": float(np.median(values)), "max": float(values.max())},
    }


def raised_half(calibration: dict | None, half: str, factor: float, evidence: dict, who: str) -> dict:
    """A two-half signal's calibration (``spread-stall``, ``choice-stall``) with ``half``'s threshold times
    ``factor`` (>= 1: a threshold fitted on the policy's own episodes is only ever raised), the
    demonstrations' threshold and the ``evidence`` kept beside it; the other half's is left as it is."""
    if not (isinstance(factor, int | float) and math.isfinite(factor) and factor >= 1):
        raise SignalError(f"{who}: a threshold fitted on episodes can only be raised, got factor {factor!r}")
    if calibration is None:
        raise SignalError(f"{who}: calibrate before fitting a threshold on episodes")
    record = dict(calibration[half])
    record["demonstrations_threshold"] = record.get("demonstrations_threshold", record["threshold"])
    record["threshold"] = float(record["threshold"]) * float(factor)
    record["own_episodes"] = dict(evidence) | {"factor": float(factor)}
    return dict(calibration) | {half: record}


def check_quantile(name: str, q: float) -> None:
    if not (isinstance(q, int | float) and 0 < q < 1):
        raise ValueError(f"{name} must be in (0, 1), got {q!r}")


def check_positive_int(name: str, v: object) -> None:
    if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
        raise ValueError(f"{name} must be an integer >= 1, got {v!r}")


@dataclass(frozen=True)
class SignalConfig:
    """Base of every signal's config; ``seed`` makes its sampling reproducible."""

    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


SCENES = ("familiar", "new")  # the policy's training scene, and one outside its demonstrations


class AssistanceSignal(ABC):
    """Base class. Subclasses set ``name`` and ``Config`` and implement ``score`` and ``_calibrate``."""

    name: ClassVar[str]
    Config: ClassVar[type[SignalConfig]]
    needs_rollouts: ClassVar[bool] = False  # calibration needs the policy's own rollouts
    has_models: ClassVar[bool] = False  # auxiliary networks trained by ``hitl train-signal``
    # its thresholds can be fitted on the policy's own successful episodes (``episode_level``)
    fits_on_episodes: ClassVar[bool] = False

    def __init__(self, policy: DiffusionPolicy, config: SignalConfig | None = None) -> None:
        config = config if config is not None else self.Config()
        if not isinstance(config, self.Config):
            raise SignalError(f"signal {self.name!r} takes a {self.Config.__name__}, got {type(config).__name__}")
        self.policy = policy
        self.config = config
        self.calibration: dict | None = None
        self._generator = torch.Generator().manual_seed(config.seed)

    # -- thresholds -------------------------------------------------------------------
    @property
    def threshold(self) -> float:
        if self.calibration is None:
            raise SignalError(f"signal {self.name!r} is not calibrated: run `hitl train-signal --signal {self.name}`")
        return float(self.calibration["threshold"])

    def calibrate(self, data: CalibrationData, progress: bool = False) -> dict:
        """Sets and returns the calibration record (threshold, quantile, samples, source)."""
        if self.needs_rollouts and (data.rollouts is None or len(data.rollouts) == 0):
            raise SignalError(f"signal {self.name!r} calibrates on the policy's own rollouts; none were given")
        self.calibration = self._calibrate(data, progress)
        self.reset()
        return self.calibration

    @abstractmethod
    def _calibrate(self, data: CalibrationData, progress: bool) -> dict: ...

    def episode_level(self, scores: np.ndarray, scene: str) -> float:
        """Signals with ``fits_on_episodes``: the highest threshold at which this signal would have asked
        on an episode whose scores (one per step) were ``scores``, by its rule for a ``scene`` of
        ``SCENES`` (the policy's training scene, or a new one)."""
        raise SignalError(f"signal {self.name!r} has no rule to fit on episodes")

    def scale_threshold(self, scene: str, factor: float, evidence: dict) -> None:
        """Signals with ``fits_on_episodes``: its threshold for ``scene`` times ``factor`` (>= 1), the
        ``evidence`` recorded with the calibration."""
        raise SignalError(f"signal {self.name!r} has no rule to fit on episodes")

    # -- per step -------------------------------------------------------------------------
    def reset(self, robot_ids: Iterable[int] | None = None) -> None:  # noqa: B027 - stateless signals keep nothing
        """Forgets per-robot state (all robots when ``robot_ids`` is None)."""

    @abstractmethod
    def score(self, batch: SignalInput) -> Scores: ...

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        """(B,) bool; the default rule is ``score > threshold``."""
        return np.asarray(scores.value) > self.threshold

    def explain(self, scores: Scores, j: int) -> str | None:
        """Why robot ``j`` of ``scores`` asks, in a few words for the operator (None: the score and the
        threshold say it)."""
        return None

    def urgent(self, state: TriggerState) -> np.ndarray:
        """(B,) bool, for the robots of the last ``wants_help`` (``state``): the request cannot wait,
        because the policy's next step would undo an operator's work. A fleet's cooldown after a
        hand-back holds back every other request, not these. The default: none is."""
        return np.zeros(len(state.robot_ids), dtype=bool)

    # -- auxiliary models (signals with ``has_models``) ----------------------------------------------
    def fit(self, data: CalibrationData, steps: int, progress: bool = True) -> dict:
        raise SignalError(f"signal {self.name!r} has no auxiliary models to train")

    def model_state(self) -> dict[str, torch.Tensor]:
        return {}

    def load_model_state(self, state: dict[str, torch.Tensor]) -> None:
        if state:
            raise SignalError(f"signal {self.name!r} has no auxiliary models, got weights")

    # -- helpers -----------------------------------------------------------------------------------------
    def _ids_for(self, robot_ids: Iterable[int] | None) -> list[int] | None:
        return None if robot_ids is None else [int(i) for i in robot_ids]

    def sample_chunks(self, obs: torch.Tensor, k: int) -> torch.Tensor:
        """(B, H, D) raw obs -> (B, k, C, 10) raw chunks: k independent DDIM samples per robot in one batch."""
        b = obs.shape[0]
        rep = obs.repeat_interleave(k, dim=0)
        chunks = self.policy.predict_action_chunk(rep, generator=self._generator)
        return chunks.reshape(b, k, *chunks.shape[1:])


class RobotNoise:
    """One noise stream per robot, seeded by (seed, robot id) and restarted by ``reset``: a robot's
    draws do not depend on which other robots share its batch, or in which order."""

    def __init__(self, seed: int) -> None:
        self.seed = int(seed)
        self._generators: dict[int, torch.Generator] = {}

    def generator(self, robot_id: int) -> torch.Generator:
        rid = int(robot_id)
        if rid not in self._generators:
            state = np.random.SeedSequence([self.seed, rid]).generate_state(2, np.uint32)
            self._generators[rid] = torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))
        return self._generators[rid]

    def randn(self, robot_ids: Iterable[int], shape: tuple[int, ...]) -> torch.Tensor:
        """(B, *shape) standard normal draws, row b from robot ``robot_ids[b]``'s stream."""
        return torch.stack([torch.randn(shape, generator=self.generator(i)) for i in robot_ids])

    def rand(self, robot_ids: Iterable[int]) -> np.ndarray:
        """(B,) uniform draws in [0, 1), one from each robot's stream."""
        return np.array([float(torch.rand((), generator=self.generator(i), dtype=torch.float64)) for i in robot_ids])

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        if robot_ids is None:
            self._generators.clear()
        else:
            for i in robot_ids:
                self._generators.pop(int(i), None)


class Patience:
    """Per-robot count of consecutive steps over the threshold; a robot wants help once its count
    reaches ``patience`` (and the count restarts at the first step under it)."""

    def __init__(self, patience: int) -> None:
        self.patience = patience
        self._run = PerRobot(int)

    def update(self, over: np.ndarray, robot_ids: Iterable[int]) -> np.ndarray:
        """over: (B,) bool this step -> (B,) bool wants help."""
        out = np.zeros(len(over), dtype=bool)
        for j, rid in enumerate(robot_ids):
            count = self._run.get(int(rid)) + 1 if over[j] else 0
            self._run.set(int(rid), count)
            out[j] = count >= self.patience
        return out

    def reset(self, robot_ids: list[int] | None) -> None:
        self._run.reset(robot_ids)


class PerRobot:
    """Per-robot trigger state: a dict from robot id to a value, created on first use."""

    def __init__(self, default) -> None:
        self._default = default
        self._state: dict[int, object] = {}

    def get(self, robot_id: int):
        if robot_id not in self._state:
            self._state[robot_id] = self._default()
        return self._state[robot_id]

    def set(self, robot_id: int, value) -> None:
        self._state[robot_id] = value

    def reset(self, robot_ids: list[int] | None) -> None:
        if robot_ids is None:
            self._state.clear()
        else:
            for i in robot_ids:
                self._state.pop(i, None)

"""Reference signals: ``full-teleop`` (the operator drives every step) and ``random`` (asks at random
steps at a set rate; match the rate to another signal's to see whether that signal is informative)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    RobotNoise,
    Scores,
    SignalConfig,
    SignalInput,
    TriggerState,
)


@dataclass(frozen=True)
class FullTeleopConfig(SignalConfig):
    pass


class FullTeleopSignal(AssistanceSignal):
    name = "full-teleop"
    Config = FullTeleopConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self.calibration = self._calibrate(None, False)

    def score(self, batch: SignalInput) -> Scores:
        return Scores(np.ones(len(batch)))

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return np.ones(len(scores.value), dtype=bool)

    def _calibrate(self, data: CalibrationData | None, progress: bool) -> dict:
        return {"threshold": 0.0, "quantile": None, "samples": 0, "source": "none: always asks"}


@dataclass(frozen=True)
class RandomConfig(SignalConfig):
    """Asks on a step with probability ``rate`` (score uniform in [0, 1), threshold 1 - rate)."""

    rate: float = 0.05

    def __post_init__(self) -> None:
        if not (isinstance(self.rate, int | float) and math.isfinite(self.rate) and 0 <= self.rate <= 1):
            raise ValueError(f"rate must be in [0, 1], got {self.rate!r}")


class RandomSignal(AssistanceSignal):
    name = "random"
    Config = RandomConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self._noise = RobotNoise(self.config.seed)  # each robot's draws, whatever its batch
        self.match_rate(self.config.rate)

    def match_rate(self, rate: float, source: str = "configured rate") -> None:
        """Sets the help rate, e.g. to another signal's measured rate on the same rollouts."""
        if not (math.isfinite(rate) and 0 <= rate <= 1):
            raise ValueError(f"rate must be in [0, 1], got {rate!r}")
        self.calibration = {"threshold": 1.0 - rate, "rate": rate, "quantile": None, "samples": 0, "source": source}

    def score(self, batch: SignalInput) -> Scores:
        return Scores(self._noise.rand(batch.robot_ids))

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return np.asarray(scores.value) >= self.threshold  # uniform in [0, 1): never at rate 0

    def reset(self, robot_ids=None) -> None:
        self._noise.reset(robot_ids)

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        assert self.calibration is not None
        return self.calibration

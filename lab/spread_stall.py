"""``spread-stall``: the fleet's previous asking signal, superseded by ``choice-stall``
(``policy.signals.choice_stall``); kept in the lab, registered only for the benchmarks
(``lab.signals``), for the committed results that compare with it. Where the scene is one the policy
knows, it asks when the policy is unsure (``spread``); where the scene is new, it asks when the policy
is stuck (``stall``, with ``reask_undo``).

Why (docs/signals.md, "spread-stall"; docs/benchmarks/hitl.md):

- ``spread`` reads the denoising field. On the scenes the policy was trained on it finds the states
  where its actions disagree: the drawer to choose, the cup's blind insertion. But on a scene outside
  its training range the field is extrapolation. On lift-hammer, with the object-frame lift policy,
  ``spread`` wants help at every step of the episode, the approach (which the policy does well)
  included (help rate 1.00, docs/results/signals/assist-stall-lift-hammer.json), so the operator
  drives the whole episode.
- ``stall`` does not read the field (here with ``reask_undo``, so that the policy cannot undo a
  takeover, and ``closed_grace``, so that a grasp that goes nowhere asks too). It asks when the
  policy stops making progress with the gripper open: on an unseen object, above it, at the grasp it
  does not know. On the trained scenes it hardly
  asks at all (0.6% of lift-cube steps), and it misses the drawer robot that opens the wrong drawer
  without stalling.

So the scene decides which one asks. A robot's scene is *new* once the observation lies outside the
policy's training demonstrations' range by more than ``novelty_gate`` (``spread``'s novelty term: how
far outside, in units of the range, averaged over dimensions; the range is the demonstrations' the
signal was calibrated on, so a version fine-tuned on a few takeovers of an unseen object, whose
network normalizer now covers them, still finds that object's scenes new, and ``stall`` still asks
there when it is stuck). Measured on development seeds (docs/signals.md,
"spread-stall"): at most 0.048 on the scenes the policies were trained for (lift-cube, cup-stack and
open-drawer, failed episodes included), 0.36 to 0.56 at every step on the unseen objects. The gate,
0.15, sits between them with a factor of about 3 to each side. The decision is kept to the end of the
episode: the object does not change during it, and a robot that switched signals midway would be
judged by two rules in one takeover. ``reset`` forgets it.

**Fitted on the policy's own episodes** (``episode_level``, ``scale_threshold``): the fine-tuning
job raises each half's threshold to the level at which the most doubtful of the new version's own
successful episodes would have asked, ``spread``'s on the training task and ``stall``'s on the new
scenes the takeovers came from (``policy.finetune.fit_threshold_on_own_episodes``); the
demonstrations' threshold is kept beside it.

The score is the active signal's score over its own threshold, so the threshold is 1: a score of 2
means twice the calibrated level, whichever signal asks. That makes scores comparable across tasks
for the queue. The sweep of ``hitl bench hitl`` scales both thresholds together. Cost: ``spread``'s
network call; ``stall`` reads the action the controller already sampled.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from policy.signals.base import (
    SCENES,
    AssistanceSignal,
    CalibrationData,
    Patience,
    PerRobot,
    Scores,
    SignalConfig,
    SignalError,
    SignalInput,
    TriggerState,
    check_positive_int,
    check_quantile,
    raised_half,
)
from policy.signals.spread import SpreadConfig, SpreadSignal
from policy.signals.stall import StallConfig, StallSignal


@dataclass(frozen=True)
class SpreadStallConfig(SignalConfig):
    """novelty_gate: observation novelty beyond which a robot's scene is new (``stall`` asks); the
    others configure the two signals as their own configs do (``spread_quantile``, ``stall_quantile``:
    their thresholds' quantiles on the validation demonstrations)."""

    novelty_gate: float = 0.15
    spread_quantile: float = 0.95
    spread_patience: int = 1  # consecutive steps over the threshold before spread asks
    num_samples: int = 32
    noise_step: int = 60
    stall_quantile: float = 0.95
    patience: int = 3
    reask_undo: bool = True
    undo_min: float = 0.01  # metres
    closed_grace: int = 30  # steps: longer than a grasp and its lift hold the gripper closed

    def __post_init__(self) -> None:
        g = self.novelty_gate
        if not (isinstance(g, int | float) and not isinstance(g, bool) and math.isfinite(g) and g > 0):
            raise SignalError(f"novelty_gate must be a finite number > 0, got {g!r}")
        check_quantile("spread_quantile", self.spread_quantile)
        check_quantile("stall_quantile", self.stall_quantile)
        check_positive_int("patience", self.patience)
        check_positive_int("spread_patience", self.spread_patience)
        self.spread_config()  # each signal checks its own settings
        self.stall_config()

    def spread_config(self) -> SpreadConfig:
        return SpreadConfig(
            seed=self.seed, num_samples=self.num_samples, noise_step=self.noise_step, quantile=self.spread_quantile
        )

    def stall_config(self) -> StallConfig:
        return StallConfig(
            seed=self.seed,
            quantile=self.stall_quantile,
            patience=self.patience,
            reask_undo=self.reask_undo,
            undo_min=self.undo_min,
            closed_grace=self.closed_grace,
        )


FLOOR = 1e-9  # a threshold at or under 0 counts as this: any positive score is far over it


def _half(scene: str) -> str:
    """The half that asks on ``scene``."""
    if scene not in SCENES:
        raise SignalError(f"spread-stall: scene must be one of {SCENES}, got {scene!r}")
    return "spread" if scene == "familiar" else "stall"


def _over(score: np.ndarray, threshold: float) -> np.ndarray:
    """The score in units of its threshold. A calibration can give 0 (``stall``: the policy never stood
    still on the validation steps); the score is then divided by ``FLOOR``, so it stays finite."""
    return score / (threshold if threshold > 0 else FLOOR)


class SpreadStallSignal(AssistanceSignal):
    name = "spread-stall"
    Config = SpreadStallConfig
    fits_on_episodes = True

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self.spread = SpreadSignal(policy, self.config.spread_config())
        self.stall = StallSignal(policy, self.config.stall_config())
        self._new = PerRobot(bool)  # the robot's scene this episode is outside the training range
        self._unsure = Patience(self.config.spread_patience)
        self._parts: tuple[np.ndarray, Scores] | None = None  # the scored batch: robot ids, stall's scores
        self._new_now: np.ndarray | None = None  # the last wants_help: which robots' scenes are new

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        ids = self._ids_for(robot_ids)
        self.spread.reset(ids)
        self.stall.reset(ids)
        self._new.reset(ids)
        self._unsure.reset(ids)

    def _thresholds(self) -> tuple[float, float]:
        """Each signal's own threshold (1, 1 before calibration: the scores in their own units)."""
        if self.calibration is None:
            return 1.0, 1.0
        return float(self.calibration["spread"]["threshold"]), float(self.calibration["stall"]["threshold"])

    def _sync(self) -> None:
        """The two signals score with the calibration this one holds (loaded, calibrated or swept)."""
        cal = self.calibration
        self.spread.calibration = None if cal is None else cal["spread"]
        self.stall.calibration = None if cal is None else cal["stall"]

    def score(self, batch: SignalInput) -> Scores:
        self._sync()
        if batch.action is None:  # both halves score the same sampled action
            action = self.sample_chunks(batch.obs, 1)[:, 0]
            batch = SignalInput(batch.obs, batch.current, batch.robot_ids, action, batch.operator_action)
        spread, stall = self.spread.score(batch), self.stall.score(batch)
        novelty = np.asarray(spread.parts["novelty"], dtype=np.float64)
        new = np.zeros(len(batch), dtype=bool)
        for j, rid in enumerate(int(r) for r in batch.robot_ids):
            if novelty[j] > self.config.novelty_gate:
                self._new.set(rid, True)
            new[j] = self._new.get(rid)
        t_spread, t_stall = self._thresholds()
        over_spread = _over(np.asarray(spread.value, dtype=np.float64), t_spread)
        over_stall = _over(np.asarray(stall.value, dtype=np.float64), t_stall)
        self._parts = (batch.robot_ids.copy(), stall)
        parts = {
            "new_scene": new.astype(np.float64),
            "novelty": novelty,
            "spread": over_spread,
            "stall": over_stall,
        }
        return Scores(np.where(new, over_stall, over_spread), parts)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        if self._parts is None or not np.array_equal(self._parts[0], state.robot_ids):
            raise SignalError("spread-stall: wants_help must follow score on the same robots")
        t = self.threshold
        new = np.asarray(scores.parts["new_scene"]) > 0
        stuck = self.stall.trigger(np.asarray(scores.parts["stall"]) > t, self._parts[1], state)
        unsure = self._unsure.update(np.asarray(scores.parts["spread"]) > t, state.robot_ids)
        self._new_now = new
        return np.where(new, stuck, unsure)

    def urgent(self, state: TriggerState) -> np.ndarray:
        """``stall``'s urgent requests (``reask_undo``), where the scene is new and so ``stall`` asks."""
        urgent = self.stall.urgent(state)  # raises unless wants_help ran on these robots
        if self._new_now is None or len(self._new_now) != len(urgent):
            raise SignalError("spread-stall: urgent must follow wants_help on the same robots")
        return urgent & self._new_now

    def explain(self, scores: Scores, j: int) -> str | None:
        if scores.parts["new_scene"][j] > 0:
            if not scores.parts["stall"][j] > self.threshold:  # reask_undo (urgent): the plan would undo a takeover
                return "new scene, the policy would undo the operator's work"
            return f"new scene, the policy is stuck: stall {scores.parts['stall'][j]:.2g}× its threshold"
        return f"the policy is unsure: spread {scores.parts['spread'][j]:.3g}× its threshold"

    def episode_level(self, scores: np.ndarray, scene: str) -> float:
        """The score is the asking half's over its threshold, and the robot asks once that half's
        patience (``spread_patience`` on a familiar scene, ``patience`` on a new one) of consecutive
        steps exceed this signal's threshold: the level it would have asked at is the largest value
        that many consecutive steps all reached (0 for a shorter episode). ``reask_undo`` asks only
        after a takeover, which an autonomous episode has none of."""
        v = np.asarray(scores, dtype=np.float64)
        p = self.config.spread_patience if _half(scene) == "spread" else self.config.patience
        if len(v) < p:
            return 0.0
        return float(np.lib.stride_tricks.sliding_window_view(v, p).min(axis=1).max())

    def scale_threshold(self, scene: str, factor: float, evidence: dict) -> None:
        """The asking half's threshold for ``scene`` (``spread`` on a familiar scene, ``stall`` on a new
        one) times ``factor``; the other half's is left as it is."""
        self.calibration = raised_half(self.calibration, _half(scene), factor, evidence, "spread-stall")
        self.reset()

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        spread = self.spread.calibrate(data, progress)
        stall = self.stall.calibrate(data, progress)
        return {
            "threshold": 1.0,
            "quantile": None,
            "samples": int(spread["samples"]),
            "source": "validation demonstrations: each signal's threshold, the score over it",
            "novelty_gate": self.config.novelty_gate,
            "spread": spread,
            "stall": stall,
        }

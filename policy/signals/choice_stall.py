"""``choice-stall``: the fleet's asking signal. On a scene the policy knows it asks where the policy has
a choice of where to go (``choice``); on a new scene it asks where the policy is stuck (``stall``, with
``reask_undo`` and ``closed_grace``).

Why (docs/signals.md, "choice-stall"): the floor (docs/benchmarks/hitl.md) shows where a few
operator steps change the outcome. On the drawer it is the policy's first step, where it chooses a
drawer; on the lift shifts it is the grasp of an object the policy never saw, where it stops above
the object; on cup-stack the insertion, where its targets spread around the hidden cup. ``choice``
finds the first and the last (the policy's own samples disagree on where to go), ``stall`` the
second; on a new scene ``choice`` is extrapolation.

Which half asks: a robot's scene is new once its observation lies outside the range of the
demonstrations the signal was calibrated on by more than ``novelty_gate`` (in units of that range,
averaged over dimensions; ``policy.signals.spread``), and the decision is kept to the end of the
episode (docs/signals.md gives the gate's measurement).

The score is the asking half's score over its own threshold, so the threshold is 1 (comparable across
tasks for the queue). Hand-back: ``choice``'s two thresholds (``return_ratio``) on a familiar scene,
``stall``'s ``reask_undo`` on a new one. Cost: ``choice``'s samples; ``stall`` reads the action the
controller already sampled, the novelty the observation.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch

from policy.signals.base import (
    AGREES,
    SCENES,
    AssistanceSignal,
    CalibrationData,
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
from policy.signals.choice import ChoiceConfig, ChoiceSignal, window_level
from policy.signals.spread import demonstrations_range, novelty_against
from policy.signals.stall import StallConfig, StallSignal
from sim.spaces import GRIPPER, POS

FLOOR = 1e-9  # the unit of a score's margin over a threshold at or under 0 (``over``)


def over(score: np.ndarray, threshold: float) -> np.ndarray:
    """The score in units of its threshold. A threshold at or under 0 (``stall``'s calibration gives 0 when
    the policy never stood still on the validation steps; a threshold set by hand may be negative) has no
    unit: the score's margin over it is taken in units of ``FLOOR``, so any score above it is far over
    it, and every score stays finite."""
    score = np.asarray(score, dtype=np.float64)
    return score / threshold if threshold > 0 else (score - threshold) / FLOOR


@dataclass(frozen=True)
class ChoiceStallConfig(SignalConfig):
    """novelty_gate: observation novelty beyond which a robot's scene is new (``stall`` asks); the
    others configure the two halves as their own configs do."""

    novelty_gate: float = 0.15
    num_samples: int = 16
    stride_ratio: float = 0.25
    choice_patience: int = 1
    return_ratio: float = 0.5
    stall_quantile: float = 0.95
    patience: int = 3
    reask_undo: bool = True
    undo_min: float = 0.01  # metres
    closed_grace: int = 30  # steps: longer than a grasp and its lift hold the gripper closed
    agree_cos: float = 0.7  # the policy agrees with the operator: their motions this close in direction
    agree_still: float = 0.003  # metres: motions shorter than this are compared by where they end

    def __post_init__(self) -> None:
        g = self.novelty_gate
        if not (isinstance(g, int | float) and not isinstance(g, bool) and math.isfinite(g) and g > 0):
            raise SignalError(f"novelty_gate must be a finite number > 0, got {g!r}")
        check_quantile("stall_quantile", self.stall_quantile)
        check_positive_int("choice_patience", self.choice_patience)
        c, m = self.agree_cos, self.agree_still
        if not (isinstance(c, int | float) and not isinstance(c, bool) and -1 < c < 1):
            raise SignalError(f"agree_cos must be a cosine in (-1, 1), got {c!r}")
        if not (isinstance(m, int | float) and not isinstance(m, bool) and math.isfinite(m) and m > 0):
            raise SignalError(f"agree_still must be a distance > 0 in metres, got {m!r}")
        self.choice_config()  # each half checks its own settings
        self.stall_config()

    def choice_config(self) -> ChoiceConfig:
        return ChoiceConfig(
            seed=self.seed,
            num_samples=self.num_samples,
            stride_ratio=self.stride_ratio,
            patience=self.choice_patience,
            return_ratio=self.return_ratio,
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


def _half(scene: str) -> str:
    if scene not in SCENES:
        raise SignalError(f"choice-stall: scene must be one of {SCENES}, got {scene!r}")
    return "choice" if scene == "familiar" else "stall"


def agrees(policy: np.ndarray, operator: np.ndarray, current: np.ndarray, cos: float, still: float) -> np.ndarray:
    """(B, 10) the policy's would-be action, the operator's, the current pose's (raw) -> (B,) bool: the
    two send the gripper the same way (open or closed) and the end effector the same way: their motions
    within ``cos`` of each other in direction, or, where either moves less than ``still``, ending within
    ``still`` of each other."""
    a, b = policy[:, POS] - current[:, POS], operator[:, POS] - current[:, POS]
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    same_way = (a * b).sum(-1) >= cos * na * nb
    near = np.linalg.norm(policy[:, POS] - operator[:, POS], axis=-1) < still
    moving = (na >= still) & (nb >= still)
    gripper = (policy[:, GRIPPER] > 0) == (operator[:, GRIPPER] > 0)
    return gripper & np.where(moving, same_way, near)


class ChoiceStallSignal(AssistanceSignal):
    name = "choice-stall"
    Config = ChoiceStallConfig
    fits_on_episodes = True

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self.choice = ChoiceSignal(policy, self.config.choice_config())
        self.stall = StallSignal(policy, self.config.stall_config())
        self._new = PerRobot(bool)  # the robot's scene this episode is outside the demonstrations' range
        self._agree_now: tuple[np.ndarray, np.ndarray] | None = None  # the scored batch: ids, agreement
        self._carry_on: np.ndarray | None = None  # the last wants_help: requests that carry on a takeover
        self._parts: tuple[np.ndarray, Scores] | None = None  # the scored batch: robot ids, stall's scores
        self._new_now: np.ndarray | None = None  # the last wants_help: which robots' scenes are new

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        ids = self._ids_for(robot_ids)
        self.choice.reset(ids)
        self.stall.reset(ids)
        self._new.reset(ids)

    def _thresholds(self) -> tuple[float, float]:
        """Each half's own threshold (1, 1 before calibration: the scores in their own units)."""
        if self.calibration is None:
            return 1.0, 1.0
        return float(self.calibration["choice"]["threshold"]), float(self.calibration["stall"]["threshold"])

    @torch.no_grad()
    def score(self, batch: SignalInput) -> Scores:
        cal = self.calibration
        self.stall.calibration = None if cal is None else cal["stall"]
        if batch.action is None:  # stall scores the action the robot takes
            action = self.sample_chunks(batch.obs, 1)[:, 0]
            batch = SignalInput(batch.obs, batch.current, batch.robot_ids, action, batch.operator_action)
        stall = self.stall.score(batch)
        novelty = novelty_against(self.policy, batch.obs, None if cal is None else cal.get("novelty_range"))
        novelty = novelty.double().numpy()
        new = np.zeros(len(batch), dtype=bool)
        for j, rid in enumerate(int(r) for r in batch.robot_ids):
            if novelty[j] > self.config.novelty_gate:
                self._new.set(rid, True)
            new[j] = self._new.get(rid)
        choice = np.zeros(len(batch))
        if not new.all():  # choice's samples only for the robots whose scene is familiar
            familiar = np.flatnonzero(~new)
            choice[familiar] = self.choice.spread(
                batch.obs[familiar], batch.current[familiar], batch.robot_ids[familiar]
            )
        t_choice, t_stall = self._thresholds()
        over_choice, over_stall = over(choice, t_choice), over(stall.value, t_stall)
        self._parts = (batch.robot_ids.copy(), stall)
        agree = np.full(len(batch), np.nan)  # NaN where no operator drives the robot
        if batch.operator_action is not None:  # the operator's robots: does the policy's plan go their way?
            op = batch.operator_action.double().numpy()
            driven = np.isfinite(op).all(axis=-1)
            if driven.any():
                plan = batch.action[:, 0].double().numpy()
                cfg = self.config
                agree[driven] = agrees(
                    plan[driven], op[driven], batch.current.double().numpy()[driven], cfg.agree_cos, cfg.agree_still
                ).astype(np.float64)
        self._agree_now = (batch.robot_ids.copy(), agree)
        parts = {
            "new_scene": new.astype(np.float64),
            "novelty": novelty,
            "choice": over_choice,
            "choice_m": choice,
            "stall": over_stall,
            AGREES: agree,
        }
        return Scores(np.where(new, over_stall, over_choice), parts)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        if self._parts is None or not np.array_equal(self._parts[0], state.robot_ids):
            raise SignalError("choice-stall: wants_help must follow score on the same robots")
        t = self.threshold
        new = np.asarray(scores.parts["new_scene"]) > 0
        stuck = self.stall.trigger(np.asarray(scores.parts["stall"]) > t, self._parts[1], state)
        unsure = self.choice.trigger(np.asarray(scores.parts["choice"], dtype=np.float64), t, state.robot_ids)
        wants = np.where(new, stuck, unsure)
        out, carry_on = self._hand_back(wants, state)
        self._new_now = new
        self._carry_on = carry_on
        return out

    def _hand_back(self, wants: np.ndarray, state: TriggerState) -> tuple[np.ndarray, np.ndarray]:
        """The hand-back rule (ThriftyDAgger's switch-back): a robot that asked keeps wanting help, request
        after request, until the policy, scored in shadow on the operator's step, agrees with them
        (``agrees``). On the operator's steps it wants help while the policy disagrees (what a controller's
        ``return_after`` counts); on the first policy step after a takeover it asks again when the policy
        did not agree with the operator's last step. The request's state (engaged, the last agreement) is
        the robot's control state's (``state``); this signal keeps none. Returns (wants help, which of them
        carry on a takeover)."""
        if self._agree_now is None or not np.array_equal(self._agree_now[0], state.robot_ids):
            raise SignalError("choice-stall: wants_help must follow score on the same robots")
        agree = self._agree_now[1]
        out, carry_on = np.asarray(wants, dtype=bool).copy(), np.zeros(len(wants), dtype=bool)
        engaged, agreed = state.engaged, state.agreed
        driven = state.teleop & engaged
        out[driven] = ~(agree[driven] > 0)
        after = ~state.teleop & engaged & np.isfinite(agreed)  # the first policy step after a takeover
        settled = after & (agreed > 0)  # handed back for good (a new request needs the ask level again)
        if settled.any():
            self.choice.release(state.robot_ids[settled])
            out[settled] = False
        unsettled = after & ~(agreed > 0)
        carry_on[unsettled] = ~np.asarray(wants, dtype=bool)[unsettled]
        out[unsettled] = True
        return out, carry_on

    def urgent(self, state: TriggerState) -> np.ndarray:
        """``stall``'s urgent requests (``reask_undo``), where the scene is new and so ``stall`` asks."""
        urgent = self.stall.urgent(state)  # raises unless wants_help ran on these robots
        if self._new_now is None or len(self._new_now) != len(urgent):
            raise SignalError("choice-stall: urgent must follow wants_help on the same robots")
        return urgent & self._new_now

    def explain(self, scores: Scores, j: int) -> str | None:
        if self._carry_on is not None and j < len(self._carry_on) and self._carry_on[j]:
            return "the policy does not agree with the operator's last step: carry on"
        if scores.parts["new_scene"][j] > 0:
            if not scores.parts["stall"][j] > self.threshold:  # reask_undo (urgent): the plan would undo a takeover
                return "new scene, the policy would undo the operator's work"
            return f"new scene, the policy is stuck: stall {scores.parts['stall'][j]:.2g}× its threshold"
        cm, ratio = 100 * float(scores.parts["choice_m"][j]), float(scores.parts["choice"][j])
        return f"the policy has a choice of which way to go: targets {cm:.2g} cm to either side ({ratio:.2g}×)"

    def episode_level(self, scores: np.ndarray, scene: str) -> float:
        """The score is the asking half's over its threshold, and the robot asks once that half's
        patience of consecutive steps exceed this signal's threshold: the level it would have asked at
        is the largest value that many consecutive steps all reached. ``reask_undo`` asks only after a
        takeover, which an autonomous episode has none of."""
        return window_level(scores, self.config.choice_patience if _half(scene) == "choice" else self.config.patience)

    def scale_threshold(self, scene: str, factor: float, evidence: dict) -> None:
        """The asking half's threshold for ``scene`` times ``factor``; the other half's is left as it is."""
        self.calibration = raised_half(self.calibration, _half(scene), factor, evidence, "choice-stall")
        self.reset()

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        choice = self.choice.calibrate(data, progress)
        stall = self.stall.calibrate(data, progress)
        return {
            "threshold": 1.0,
            "quantile": None,
            "samples": int(choice["samples"]),
            "source": "validation demonstrations: each half's threshold, the score over it",
            "novelty_gate": self.config.novelty_gate,
            "novelty_range": demonstrations_range(self.policy, data.train.obs),
            "choice": choice,
            "stall": stall,
        }

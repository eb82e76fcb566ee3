"""``stall``: ask when the policy stops making progress: its next action barely moves the end effector,
with the gripper open (or, with ``closed_grace``, closed for longer than a grasp takes), for
``patience`` steps in a row.

Why (docs/signals.md, "stall"; docs/benchmarks/finetune.md, "Whole takeovers: asking when the policy
is stuck"): on an object it has never seen, the object-frame lift policy approaches well (the
approach depends on where the object is, which it knows) and then stops above the object, open,
because it does not know where this shape is grasped. That is the state that needs help. The uncertainty
signals ask at the first step instead: the new object's extent is outside everything the policy was
trained on, so every step of the episode looks uncertain, and the operator ends up driving whole
episodes.

A step's *stillness* is how much less than its usual stride the policy moves:

    motion = |p_next - p_now| / n           (m per step; p_next the position the chunk reaches after
                                             its n executed steps, p_now the current end effector)
    stillness = max(0, 1 - motion / stride)  (0 at the usual stride or faster, 1 standing still)

with ``stride`` the median motion of the policy at the open-gripper steps of the held-out
demonstrations, and stillness 0 while the gripper is closed or the policy is closing it (a grasp
holds still on purpose). The threshold is the ``quantile`` of stillness over those steps; the robot
asks after ``patience`` consecutive steps over it. No observation term: the signal does not care
whether the scene is new, only whether the policy is stuck in it.

**Keeping the operator's progress** (``reask_undo``). On the paper's protocol the operator gets 4
steps per request, fewer than a grasp takes, and between two requests the policy, which cannot do
the grasp, heads straight back to the pose where it stopped: the operator's bursts never add up
(docs/benchmarks/hitl.md, "The object-frame lift policy"). With ``reask_undo`` the first policy step
after a takeover asks again at once when its plan would undo the takeover: with the gripper open,
the operator moved the end effector more than ``undo_min`` from where the robot asked (across the
table, or up and down) and more than half of the policy's next motion that way goes back. And while
a grasp the operator closed still holds, every policy step that would open the gripper asks again:
a policy that cannot do the grasp does not know to keep it either, and reopens it a few steps into
the lift (the object drops and the operator grasps it again; docs/signals.md). The robot holds
instead, and the operator carries on from where they left it.
A plan that goes anywhere else (lifting the object the operator grasped) runs.

**A grasp that goes nowhere** (``closed_grace``). Stillness is 0 while the gripper is closed: a grasp
holds still on purpose while the fingers close. But a policy that closed on nothing, or on an object
it cannot lift, then stands still, closed, to the end of the episode. With ``closed_grace`` = n,
standing still counts again once the gripper has been closed for more than n scored steps in a row.

Both are off by default, as every ``stall`` result recorded before them was. ``reask_undo``'s requests
are ``urgent``: a fleet's cooldown after a hand-back (``cooldown``) does not hold them back, since
the policy step it would let run is the one that undoes the takeover.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from policy.signals.base import (
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
    quantile_record,
)
from sim.spaces import GRIPPER, POS


@dataclass(frozen=True)
class StallConfig(SignalConfig):
    """quantile: of the open-gripper validation steps' stillness (the threshold); patience: consecutive
    steps over it before the robot asks; calibration_batch: validation steps per policy call."""

    quantile: float = 0.95
    patience: int = 3
    calibration_batch: int = 256
    reask_undo: bool = False
    undo_min: float = 0.01  # metres
    closed_grace: int = 0  # 0: off; else closed-gripper steps after which standing still counts too

    def __post_init__(self) -> None:
        check_quantile("quantile", self.quantile)
        check_positive_int("patience", self.patience)
        check_positive_int("calibration_batch", self.calibration_batch)
        if not isinstance(self.reask_undo, bool):
            raise SignalError(f"reask_undo must be true or false, got {self.reask_undo!r}")
        if not (isinstance(self.undo_min, int | float) and not isinstance(self.undo_min, bool) and self.undo_min > 0):
            raise SignalError(f"undo_min must be a distance > 0 in metres, got {self.undo_min!r}")
        g = self.closed_grace
        if not (isinstance(g, int) and not isinstance(g, bool) and g >= 0):
            raise SignalError(f"closed_grace must be an integer >= 0, got {g!r}")


def policy_motion(action: torch.Tensor, current: torch.Tensor, n_action_steps: int) -> torch.Tensor:
    """(B, C, 10) raw chunk, (B, 10) raw current pose action -> (B,) metres per executed step from the
    current position to where the chunk's ``n_action_steps``-th action goes."""
    n = min(int(n_action_steps), action.shape[1])
    return (action[:, n - 1, POS] - current[:, POS]).double().norm(dim=-1) / n


def gripper_open(action: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the gripper is commanded open now and the chunk's first action keeps it open."""
    return (current[:, GRIPPER] <= 0) & (action[:, 0, GRIPPER] <= 0)


class StallSignal(AssistanceSignal):
    name = "stall"
    Config = StallConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        self._run = Patience(self.config.patience)
        self._asked_at = PerRobot(lambda: None)  # where the robot stood when it last asked on its own
        self._grasp_kept = PerRobot(bool)  # the gripper is closed as an operator left it
        self._closed_for = PerRobot(int)  # consecutive scored steps with the gripper closed
        self._where: tuple[np.ndarray, ...] | None = None  # the scored batch's geometry and gripper
        self._urgent: tuple[np.ndarray, np.ndarray] | None = None  # the last trigger's robot ids, reask_undo's asks

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        ids = self._ids_for(robot_ids)
        for state in (self._run, self._asked_at, self._grasp_kept, self._closed_for):
            state.reset(ids)

    def _parts(self, obs: torch.Tensor, current: torch.Tensor, action: torch.Tensor | None) -> dict[str, np.ndarray]:
        if action is None:
            action = self.sample_chunks(obs, 1)[:, 0]
        motion = policy_motion(action, current, self.policy.config.n_action_steps)
        return {"motion": motion.numpy(), "open": gripper_open(action, current).numpy().astype(np.float64)}

    def _stillness(self, parts: dict[str, np.ndarray], stride: float) -> np.ndarray:
        return np.where(parts["open"] > 0, np.clip(1 - parts["motion"] / stride, 0.0, 1.0), 0.0)

    @torch.no_grad()
    def score(self, batch: SignalInput) -> Scores:
        """Before calibration the stride is 1 cm per step."""
        action = batch.action if batch.action is not None else self.sample_chunks(batch.obs, 1)[:, 0]
        parts = self._parts(batch.obs, batch.current, action)
        if self.config.reask_undo:  # what ``wants_help`` compares after a takeover
            n = min(int(self.policy.config.n_action_steps), action.shape[1])
            self._where = (
                batch.robot_ids.copy(),
                batch.current[:, POS].double().numpy(),
                action[:, n - 1, POS].double().numpy(),
                (batch.current[:, GRIPPER] > 0).numpy(),
                (action[:, 0, GRIPPER] <= 0).numpy(),
            )
        stride = (self.calibration or {}).get("stride", 0.01)
        still = self._stillness(parts, stride)
        grace = self.config.closed_grace
        if grace:  # a gripper closed on nothing (or on a grasp that does not lift) for longer than a grasp takes
            closed = (batch.current[:, GRIPPER] > 0).numpy()
            for j, rid in enumerate(int(r) for r in batch.robot_ids):
                self._closed_for.set(rid, self._closed_for.get(rid) + 1 if closed[j] else 0)
                if self._closed_for.get(rid) > grace:
                    still[j] = max(0.0, 1.0 - float(parts["motion"][j]) / stride)
        return Scores(still, parts)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return self.trigger(np.asarray(scores.value) > self.threshold, scores, state)

    def trigger(self, over: np.ndarray, scores: Scores, state: TriggerState) -> np.ndarray:
        """The rule behind ``wants_help``, given which robots are over the threshold this step (a signal
        that holds a ``stall`` applies its own threshold): ``patience`` steps in a row, and with
        ``reask_undo`` the checks after a takeover. ``scores`` are this signal's, from ``score``."""
        out = self._run.update(np.asarray(over, dtype=bool), state.robot_ids)
        urgent = np.zeros(len(out), dtype=bool)
        self._urgent = (state.robot_ids.copy(), urgent)
        if not self.config.reask_undo:
            return out
        where = self._where
        if where is None or not np.array_equal(where[0], state.robot_ids):
            raise SignalError("stall: wants_help must follow score on the same robots")
        _, now, plan, closed, opens = where
        opened = np.asarray(scores.parts["open"]) > 0
        for j, rid in enumerate(int(r) for r in state.robot_ids):
            if state.teleop[j]:
                continue
            asked = self._asked_at.get(rid)
            if state.after_takeover[j]:  # an operator drove it since its last policy step
                self._grasp_kept.set(rid, bool(closed[j]))
                if opened[j] and asked is not None and self._heads_back(now[j], plan[j], asked):
                    out[j] = urgent[j] = True
                    continue  # asked again: the pose it first asked at stays the reference
            if not closed[j]:
                self._grasp_kept.set(rid, False)
            elif self._grasp_kept.get(rid) and opens[j]:
                out[j] = urgent[j] = True  # the policy would let go of the operator's grasp
                continue
            if out[j]:
                self._asked_at.set(rid, now[j].copy())
        return out

    def urgent(self, state: TriggerState) -> np.ndarray:
        """The robots that ``reask_undo`` made ask at the last ``trigger``."""
        if self._urgent is None or not np.array_equal(self._urgent[0], state.robot_ids):
            raise SignalError("stall: urgent must follow wants_help on the same robots")
        return self._urgent[1].copy()

    def _heads_back(self, now: np.ndarray, plan: np.ndarray, asked: np.ndarray) -> bool:
        """Across the table or up and down, taken apart: the operator moved the robot more than
        ``undo_min`` from ``asked``, and more than half of the policy's motion from ``now`` to ``plan``
        closes that distance again. Apart, because the policy that undoes a correction across often
        descends at the same time (and the other way round), which hides the undo in a 3D distance."""
        for axes in (slice(0, 2), slice(2, 3)):
            left = float(np.linalg.norm(now[axes] - asked[axes]))
            motion = float(np.linalg.norm(plan[axes] - now[axes]))
            back = left - float(np.linalg.norm(plan[axes] - asked[axes]))
            if left > self.config.undo_min and motion > 0 and back > 0.5 * motion:
                return True
        return False

    @torch.no_grad()
    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        val, size = data.val, self.config.calibration_batch
        chunks = []
        for i in tqdm(range(0, len(val), size), desc="calibrate stall", disable=not progress, unit="batch"):
            rows = slice(i, min(i + size, len(val)))
            obs, current = torch.as_tensor(val.obs[rows]), torch.as_tensor(val.current[rows])
            chunks.append(self._parts(obs, current, None))
        if not chunks:
            raise SignalError("stall: no validation demonstrations to calibrate on")
        parts = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
        moving = parts["open"] > 0
        if not moving.any():
            raise SignalError("stall: the validation demonstrations have no open-gripper steps")
        stride = float(np.median(parts["motion"][moving]))
        if not stride > 0:
            raise SignalError("stall: the policy does not move at the validation demonstrations' open-gripper steps")
        still = self._stillness({k: v[moving] for k, v in parts.items()}, stride)
        record = quantile_record(still, self.config.quantile, "validation demonstrations (open gripper)")
        return {**record, "stride": stride}

"""``stall``: ask when the policy stops making progress: its next action barely moves the end effector,
with the gripper open, for ``patience`` steps in a row.

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
holds still on purpose). The threshold is the ``quantile`` of stillness over those steps (the
policy moves slower than that on 5% of them); the robot
asks after ``patience`` consecutive steps over it. No observation term: the signal does not care
whether the scene is new, only whether the policy is stuck in it.
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

    def __post_init__(self) -> None:
        check_quantile("quantile", self.quantile)
        check_positive_int("patience", self.patience)
        check_positive_int("calibration_batch", self.calibration_batch)


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

    def reset(self, robot_ids: Iterable[int] | None = None) -> None:
        self._run.reset(self._ids_for(robot_ids))

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
        parts = self._parts(batch.obs, batch.current, batch.action)
        stride = (self.calibration or {}).get("stride", 0.01)
        return Scores(self._stillness(parts, stride), parts)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        return self._run.update(np.asarray(scores.value) > self.threshold, state.robot_ids)

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

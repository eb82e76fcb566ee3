"""Signals with learned auxiliary models: ``thrifty`` (ThriftyDAgger: ensemble novelty and Q-risk,
with switch-back) and ``hula-offline`` (variance of an ensemble CQL critic's value estimate).

Both train with ``fit`` (``hitl train-signal``) on the demonstrations' training split plus the
policy's own rollouts, then calibrate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from policy.signals.aux import (
    EnsembleMLP,
    QTraining,
    Transitions,
    features,
    norm_action,
    q_values,
    train_bc_ensemble,
    train_q,
)
from policy.signals.base import (
    AssistanceSignal,
    CalibrationData,
    Scores,
    SignalConfig,
    SignalError,
    SignalInput,
    StepSet,
    TriggerState,
    check_positive_int,
    check_quantile,
    quantile_record,
)


def _check_gamma(gamma: float) -> None:
    if not (isinstance(gamma, int | float) and 0 < gamma < 1):
        raise ValueError(f"gamma must be in (0, 1), got {gamma!r}")


class _ModelSignal(AssistanceSignal):
    has_models = True
    needs_rollouts = True

    def _robot_action(self, batch: SignalInput) -> torch.Tensor:
        """(B, 10) normalized action the robot would execute now."""
        action = batch.action if batch.action is not None else self.sample_chunks(batch.obs, 1)[:, 0]
        return norm_action(self.policy, action[:, 0])

    def _policy_actions(self, steps: StepSet, batch: int = 512) -> np.ndarray:
        """(M, 1, 10) raw: one sampled action per recorded step (what the robot would do there)."""
        out = [
            self.sample_chunks(torch.as_tensor(steps.obs[i : i + batch]), 1)[:, 0, :1].numpy()
            for i in range(0, len(steps), batch)
        ]
        return np.concatenate(out)

    def _require_models(self) -> None:
        if not getattr(self, "_fitted", False):
            raise SignalError(
                f"signal {self.name!r} has no trained models: run `hitl train-signal --signal {self.name}`"
            )


# -- ThriftyDAgger ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class ThriftyConfig(SignalConfig):
    """Novelty: variance across ``members`` behaviour-cloning nets. Risk: 1 - min(Q1, Q2)(o, a_robot)
    with Q the discounted success probability. Thresholds as in ThriftyDAgger: novelty at the
    ``quantile`` of held-out demonstrations, risk at the ``quantile`` over the policy's own rollout
    states; switch back when ||a_operator - a_robot||² is under the ensemble's mean training
    discrepancy and the safety Q(o, a_robot) is above its median over the rollout states."""

    members: int = 5
    hidden: tuple[int, ...] = (256, 256)
    gamma: float = 0.995
    quantile: float = 0.95
    bc_steps: int = 3000
    q_steps: int = 3000

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", tuple(self.hidden))
        if not (isinstance(self.members, int) and self.members >= 2):
            raise ValueError(f"members must be an integer >= 2, got {self.members!r}")
        _check_gamma(self.gamma)
        check_quantile("quantile", self.quantile)
        check_positive_int("bc_steps", self.bc_steps)
        check_positive_int("q_steps", self.q_steps)


class ThriftySignal(_ModelSignal):
    name = "thrifty"
    Config = ThriftyConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        cfg, pc = self.config, policy.config
        f = self.policy.seen_dim * pc.obs_horizon  # what the policy sees: its state, and its cameras' features
        self.ensemble = EnsembleMLP(cfg.members, f, pc.action_horizon * pc.action_dim, cfg.hidden)
        self.q = EnsembleMLP(2, f + pc.action_dim, 1, cfg.hidden)
        self._fitted = False

    def fit(self, data: CalibrationData, steps: int | None = None, progress: bool = True) -> dict:
        if data.rollouts is None or len(data.rollouts) == 0:
            raise SignalError("thrifty's Q-risk trains on the policy's own rollouts; none were given")
        torch.manual_seed(self.config.seed)
        obs = features(self.policy, data.train.obs)
        target = norm_action(self.policy, data.train.action).flatten(1)
        bc = train_bc_ensemble(
            self.ensemble, obs, target, steps or self.config.bc_steps, self.config.seed, progress=progress
        )
        cfg = QTraining(gamma=self.config.gamma, sigmoid=True, min_target=True)
        q = train_q(
            self.q,
            Transitions.from_steps(self.policy, data.train, data.rollouts),
            steps or self.config.q_steps,
            cfg,
            self.config.seed,
            progress,
        )
        self._fitted = True
        return {"bc_loss": float(np.mean(bc[-100:])), "q_loss": float(np.mean(q[-100:]))}

    @torch.no_grad()
    def _novelty(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (novelty (B,), ensemble mean (B, C*10)) in the normalized action space."""
        pred = self.ensemble(features(self.policy, obs))  # (E, B, C*10)
        return pred.var(dim=0, unbiased=False).mean(dim=-1), pred.mean(dim=0)

    @torch.no_grad()
    def _safety(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return q_values(self.q, features(self.policy, obs), action, sigmoid=True).min(dim=0).values

    def score(self, batch: SignalInput) -> Scores:
        self._require_models()
        cal = self.calibration or {}
        novelty, _ = self._novelty(batch.obs)
        a_robot = self._robot_action(batch)
        safety = self._safety(batch.obs, a_robot)
        risk = 1 - safety
        parts = {"novelty": novelty.double().numpy(), "risk": risk.double().numpy()}
        if batch.operator_action is not None:
            a_op = norm_action(self.policy, batch.operator_action)
            parts["discrepancy"] = ((a_op - a_robot) ** 2).sum(-1).double().numpy()  # NaN rows: no operator
        if cal:
            value = np.maximum(parts["novelty"] / cal["novelty_threshold"], parts["risk"] / cal["risk_threshold"])
        else:
            value = np.full(len(batch), np.nan)
        return Scores(value, parts)

    def wants_help(self, scores: Scores, state: TriggerState) -> np.ndarray:
        cal = self.calibration
        if cal is None:
            raise SignalError("signal 'thrifty' is not calibrated")
        ask = np.asarray(scores.value) > self.threshold  # 1.0 as calibrated: either part over its own
        disc = scores.parts.get("discrepancy")
        if disc is None:
            disc = np.full(len(ask), np.nan)
        with np.errstate(invalid="ignore"):
            switch_back = (disc < cal["switch_back_discrepancy"]) & (
                1 - scores.parts["risk"] > cal["switch_back_safety"]
            )
        return np.where(state.teleop, ~switch_back, ask)

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        self._require_models()
        with torch.no_grad():
            novelty, _ = self._novelty(torch.as_tensor(data.val.obs))
            _, mean = self._novelty(torch.as_tensor(data.train.obs))
            target = norm_action(self.policy, data.train.action[:, 0])
            d = target.shape[-1]  # the action executed now, as compared at switch-back
            discrepancy = ((mean[:, :d] - target) ** 2).sum(-1)
            roll = data.rollouts
            assert roll is not None
            acts = norm_action(self.policy, self._policy_actions(roll)[:, 0])
            safety = self._safety(torch.as_tensor(roll.obs), acts)
        nov = quantile_record(novelty.numpy(), self.config.quantile, "validation demonstrations")
        risk = quantile_record(1 - safety.numpy(), self.config.quantile, "policy rollout states")
        return {
            "threshold": 1.0,
            "quantile": self.config.quantile,
            "samples": nov["samples"],
            "source": "score = max(novelty / novelty_threshold, risk / risk_threshold)",
            "novelty_threshold": max(nov["threshold"], 1e-12),
            "novelty_samples": nov["samples"],
            "risk_threshold": max(risk["threshold"], 1e-12),
            "risk_samples": risk["samples"],
            "switch_back_discrepancy": float(discrepancy.mean()),
            "switch_back_safety": float(np.median(safety.numpy())),
        }

    def model_state(self) -> dict[str, torch.Tensor]:
        return {f"ensemble.{k}": v for k, v in self.ensemble.state_dict().items()} | {
            f"q.{k}": v for k, v in self.q.state_dict().items()
        }

    def load_model_state(self, state: dict[str, torch.Tensor]) -> None:
        self.ensemble.load_state_dict({k[9:]: v for k, v in state.items() if k.startswith("ensemble.")})
        self.q.load_state_dict({k[2:]: v for k, v in state.items() if k.startswith("q.")})
        self._fitted = True


# -- HULA, offline -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class HulaConfig(SignalConfig):
    """Variance across ``heads`` independently initialised CQL critics of V(o) = Q(o, a_robot),
    trained offline; threshold at the ``quantile`` over held-out demonstration states."""

    heads: int = 5
    hidden: tuple[int, ...] = (256, 256)
    gamma: float = 0.99
    cql_alpha: float = 1.0
    quantile: float = 0.95
    steps: int = 3000

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", tuple(self.hidden))
        if not (isinstance(self.heads, int) and self.heads >= 2):
            raise ValueError(f"heads must be an integer >= 2, got {self.heads!r}")
        _check_gamma(self.gamma)
        if not self.cql_alpha >= 0:
            raise ValueError(f"cql_alpha must be >= 0, got {self.cql_alpha!r}")
        check_quantile("quantile", self.quantile)
        check_positive_int("steps", self.steps)


class HulaSignal(_ModelSignal):
    name = "hula-offline"
    Config = HulaConfig

    def __init__(self, policy, config=None) -> None:
        super().__init__(policy, config)
        pc = policy.config
        self.critic = EnsembleMLP(
            self.config.heads, self.policy.seen_dim * pc.obs_horizon + pc.action_dim, 1, self.config.hidden
        )
        self._fitted = False

    def fit(self, data: CalibrationData, steps: int | None = None, progress: bool = True) -> dict:
        if data.rollouts is None or len(data.rollouts) == 0:
            raise SignalError(
                "hula-offline's critic trains on the demonstrations plus the policy's rollouts; no rollouts given"
            )
        torch.manual_seed(self.config.seed)
        cfg = QTraining(gamma=self.config.gamma, cql_alpha=self.config.cql_alpha)
        losses = train_q(
            self.critic,
            Transitions.from_steps(self.policy, data.train, data.rollouts),
            steps or self.config.steps,
            cfg,
            self.config.seed,
            progress,
        )
        self._fitted = True
        return {"critic_loss": float(np.mean(losses[-100:]))}

    @torch.no_grad()
    def _value_variance(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return q_values(self.critic, features(self.policy, obs), action, sigmoid=False).var(dim=0, unbiased=False)

    def score(self, batch: SignalInput) -> Scores:
        self._require_models()
        return Scores(self._value_variance(batch.obs, self._robot_action(batch)).double().numpy())

    def _calibrate(self, data: CalibrationData, progress: bool) -> dict:
        self._require_models()
        acts = norm_action(self.policy, self._policy_actions(data.val)[:, 0])
        values = self._value_variance(torch.as_tensor(data.val.obs), acts).numpy()
        return quantile_record(values, self.config.quantile, "validation demonstrations")

    def model_state(self) -> dict[str, torch.Tensor]:
        return {f"critic.{k}": v for k, v in self.critic.state_dict().items()}

    def load_model_state(self, state: dict[str, torch.Tensor]) -> None:
        self.critic.load_state_dict({k[7:]: v for k, v in state.items() if k.startswith("critic.")})
        self._fitted = True

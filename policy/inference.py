"""The controller's batched network calls behind one seam: ``Inference``.

A controller's step (``policy.controller``) makes one call per tick, ``run(request)``, for the robots
it scores: the policy's action chunks for those with nothing queued, then, for the whole batch, every
signal's score and decision (``wants_help``), the asking signal's urgent requests and the explanation
of each robot it wants to ask for. The controller keeps everything else: the robots' histories,
queues, control states (``policy.hitl_state``) and the decisions built on these answers. It stays the
one control step; a back end only computes.

``LocalInference`` computes here, on the policy and signals the controller was built with. Another
back end computes elsewhere on its own copies, loaded from the same policy folder
(``server.inference``: a Ray actor, on a GPU node where one is present). The signals' per-robot scoring
memory (patience runs, latches, noise) then lives there, which is why ``reset`` (a robot's new
episode, or its leaving) goes through the seam as well; what a robot's takeovers were travels in the
request, from its control state.

A back end that cannot answer raises ``InferenceUnavailable``; the controller then holds the robots
the policy drives for that step (operators' commands still go through) and asks again at the next.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from policy.diffusion_policy import DiffusionPolicy
from policy.signals.base import AssistanceSignal, Scores, SignalInput, TriggerState


class InferenceUnavailable(RuntimeError):
    """The back end could not answer this step (its process died, or is restarting)."""


@dataclass
class InferenceRequest:
    """One step's batch. obs: (B, obs_horizon, obs_dim); current: (B, 10) the poses held now; plans:
    (B, action_horizon, 10), the queued robots' plans (rows in ``need`` are filled by ``run`` from
    ``noise``, (len(need), action_horizon, 10)); teleop: (B,) under an operator; operator: (B, 10) their
    actions (NaN elsewhere) or None; asking: the signal whose urgent requests and explanations are
    wanted (None: no robot may ask this step); engaged / agreed / after_takeover: each robot's takeover
    facts from its control state (``TriggerState``); images: for a policy that sees cameras, each camera's
    frames of the histories, {camera: (B, obs_horizon, size, size, 3) uint8}, encoded where the policy runs."""

    obs: torch.Tensor
    current: torch.Tensor
    robot_ids: np.ndarray
    need: list[int]
    noise: torch.Tensor | None
    plans: torch.Tensor
    teleop: np.ndarray
    operator: torch.Tensor | None
    asking: str | None
    engaged: np.ndarray | None = None
    agreed: np.ndarray | None = None
    after_takeover: np.ndarray | None = None
    images: dict[str, torch.Tensor] | None = None

    def trigger_state(self) -> TriggerState:
        return TriggerState(
            np.asarray(self.robot_ids),
            np.asarray(self.teleop, dtype=bool).copy(),
            self.engaged,
            self.agreed,
            self.after_takeover,
        )


@dataclass
class InferenceResult:
    """plans: the request's, with the fresh chunks; scores: every signal's; wants: every calibrated
    signal's decision (B,); urgent: the asking signal's urgent requests (B,) or None; why: row -> the
    asking signal's explanation, for the rows not under teleop where it wants help (those that may ask);
    cpu_s: the CPU time (of the computing thread) the policy's chunks and each signal took in this call
    ("encode": the cameras' encoders); seen: (B, obs_horizon, seen_dim) what the policy made of the
    observations with its cameras (``DiffusionPolicy.encode_observation``), None for a state-only policy."""

    plans: torch.Tensor
    scores: dict[str, Scores]
    wants: dict[str, np.ndarray]
    urgent: np.ndarray | None
    why: dict[int, str | None]
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds of this call: "policy", each signal
    seen: torch.Tensor | None = None


class Inference(ABC):
    @abstractmethod
    def run(self, request: InferenceRequest) -> InferenceResult: ...

    @abstractmethod
    def reset(self, robot_ids: Iterable[int]) -> None:
        """The signals forget these robots (a new episode, or the robot left the controller)."""

    def close(self) -> None:  # noqa: B027 - a back end in this process holds nothing to close
        """Releases what the back end holds elsewhere (an actor)."""


def compute(policy: DiffusionPolicy, signals: Mapping[str, AssistanceSignal], req: InferenceRequest) -> InferenceResult:
    """What ``run`` answers, computed here with ``policy`` and ``signals``."""
    plans = req.plans
    clock = time.thread_time()
    cpu: dict[str, float] = {}

    def spent(part: str) -> None:
        nonlocal clock
        now = time.thread_time()
        cpu[part] = cpu.get(part, 0.0) + now - clock
        clock = now

    with torch.no_grad():
        seen = None
        if policy.config.cameras:  # once per robot-step: the chunks, the probes and every signal reuse it
            seen = policy.encode_observation(req.obs, req.images).cpu()
            spent("encode")
        obs = req.obs if seen is None else seen
        if req.need:
            plans[req.need] = policy.predict_action_chunk(obs[req.need], noise=req.noise).float().cpu()
        spent("policy")
        batch = SignalInput(obs, req.current, req.robot_ids, action=plans, operator_action=req.operator)
        scores = {}
        for name, s in signals.items():
            scores[name] = s.score(batch)
            spent(name)
    state = req.trigger_state()
    wants = {}
    for name, s in signals.items():
        if s.calibration is not None:
            wants[name] = np.asarray(s.wants_help(scores[name], state), dtype=bool)
            spent(name)
    urgent, why = None, {}
    if req.asking is not None and req.asking in wants:
        signal = signals[req.asking]
        check = getattr(signal, "urgent", None)  # optional for duck-typed signals
        urgent = np.asarray(check(state), dtype=bool) if check is not None else np.zeros(len(req.robot_ids), bool)
        explain = getattr(signal, "explain", None)
        asks = np.flatnonzero(wants[req.asking] & ~state.teleop)  # only a robot the policy drives asks
        why = {int(j): explain(scores[req.asking], int(j)) if explain else None for j in asks}
        spent(req.asking)
    return InferenceResult(plans, scores, wants, urgent, why, cpu, seen)


class LocalInference(Inference):
    """The controller's policy and signals, called in this process."""

    def __init__(self, policy: DiffusionPolicy, signals: Mapping[str, AssistanceSignal]) -> None:
        self.policy, self.signals = policy, signals

    def run(self, request: InferenceRequest) -> InferenceResult:
        return compute(self.policy, self.signals, request)

    def reset(self, robot_ids: Iterable[int]) -> None:
        ids = list(robot_ids)
        for signal in self.signals.values():
            signal.reset(ids)

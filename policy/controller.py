"""The one control step: every loop that moves robots calls ``Controller.step``.

The fleet (``server.fleet``), autonomous evaluation (``policy.evaluate``: ``hitl rollout``,
``hitl report sanity``) and assisted rollouts (``lab.assisted``: ``hitl assist`` and the
benchmarks) are thin drivers around it, so what we evaluate and benchmark is what we serve.

Per robot, keyed by robot id, the controller owns:

- the observation history (``obs_horizon`` frames; filled with the first frame of an episode, and
  again after a hand-back unless ``resume = "history"`` keeps the takeover's frames), with the frames
  of the cameras a policy that sees them sees (``RobotFrame.images``); the inference back end encodes
  them once per robot-step (``DiffusionPolicy.encode_observation``), batched across the robots;
- the action-chunk queue: a chunk is sampled when the queue is empty and its first
  ``n_action_steps`` actions are executed in turn, as in training and evaluation;
- its seeded sampling noise: each episode's DDIM noise comes from a generator seeded by the
  controller's seed and the episode seed, so a robot's actions do not depend on which other robots
  share its batch;
- its control state, ``policy.hitl_state.RobotControl`` (the fleet passes the robot's own; the one
  record of its mode and counters): ``autonomous`` (the policy acts), ``waiting`` (it asked for help
  and holds its pose) or ``teleop`` (an operator's commands drive it). The signals keep only their
  scoring memory; what a robot's takeovers were reaches their trigger rules from that state
  (``TriggerState``), and is consulted for teleoperated robots too (switch-back rules).

One step takes each robot's new ``RobotFrame`` and any operator command, and returns each robot's
action, its source (``policy``, ``operator``, ``hold``), every signal's score and decision, and
whether the robot asked for help or got control back. A robot under teleop that has no command this
step holds the last target; waiting robots hold without being scored.

Hand-back: ``budgeted`` returns control after ``budget`` operator steps (or sooner with
``return_after``); ``continuous`` keeps the operator in control until they hand back (``release``),
or, with ``return_after``, after that many consecutive operator steps on which the asking signal no
longer wants help (ThriftyDAgger's switch-back rule, or the score back under its threshold: the
paper's continuous mode is ``return_after = 1``). After a hand-back the robot does not ask again for
``cooldown`` policy steps, unless the signal's request is ``urgent`` (``AssistanceSignal.urgent``: the
policy's next step would undo the takeover, so holding the request back would lose the operator's
work). The ``watchdog`` makes a robot ask once per episode when it has used that
fraction of its horizon without success, whatever its signal says. An asking signal that scores the
policy's agreement with the operator (``Scores.parts["agrees"]``) keeps wanting help, request after
request, until the policy agrees with the operator's last step (``TriggerState``: ThriftyDAgger's
switch-back with the policy scored in shadow); the control state keeps that agreement for the signal.

Episodes: waiting for help holds the robot without using up the horizon (hold steps do not count,
``Task.step``); operator steps count, as in the paper; a timeout never ends an episode under an
operator's hands (``ends_episode``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from policy.diffusion_policy import DiffusionPolicy
from policy.hand_back import ControllerConfig
from policy.hitl_state import Mode, RobotControl
from policy.inference import Inference, InferenceRequest, InferenceUnavailable, LocalInference
from policy.signals.base import AGREES, AssistanceSignal, SignalError
from policy.uncertainty import UncertaintyBatch, UncertaintyResult
from sim.frame import RobotFrame
from sim.spaces import ACTION_DIM, ActionSpace, TeleopCommand, TeleopTarget
from storage import keys

WATCHDOG = "watchdog"  # RobotStep.asked_by when the robot asked because its episode ran long


@dataclass
class RobotStep:
    """What the controller decided for one robot at one step.

    action: (10,) raw absolute action to send; source: ``keys.SOURCE_*``; asked: the robot asked for
    help at this step (it now waits and holds), asked_by: what made it ask, why: the asking signal's
    words for it (``AssistanceSignal.explain``; None for the watchdog); returned: control went back
    to the policy after this step; scores / wants: every signal's score and decision (empty when the
    robot was not scored: waiting, or under teleop without a command); uncertainty: the denoising
    field when scored; obs: (H, obs_dim) the state history the policy saw, seen: (H, seen_dim) what it made
    of it with its cameras' frames (``DiffusionPolicy.encode_observation``; obs itself for a state-only
    policy); current: (10,) the probe centre's
    raw action; command / target: the operator command applied and what it became; unavailable: why
    nothing was scored (``policy.inference.InferenceUnavailable``: a robot the policy drives held).
    """

    robot_id: int
    action: np.ndarray
    source: str
    mode: Mode  # the mode after this step
    asked: bool = False
    asked_by: str | None = None  # the asking signal's name, or WATCHDOG
    why: str | None = None
    returned: bool = False
    scores: dict[str, float] = field(default_factory=dict)
    wants: dict[str, bool] = field(default_factory=dict)
    uncertainty: UncertaintyResult | None = None
    obs: np.ndarray | None = None
    seen: np.ndarray | None = None
    current: np.ndarray | None = None
    command: TeleopCommand | None = None
    target: TeleopTarget | None = None
    unavailable: str | None = None  # the inference back end could not answer: the policy's robots held


@dataclass
class _Robot:
    """What the controller keeps of a robot besides its control state: the policy's own execution."""

    generator: torch.Generator
    control: RobotControl
    history: deque = field(default_factory=deque)  # (obs, images) per step: the state and each camera's frame
    queue: deque = field(default_factory=deque)


ActionSink = Callable[[int, np.ndarray, str], None]


def ends_episode(frame: RobotFrame, mode: Mode) -> bool:
    """Whether ``frame`` ends its robot's episode: at success, or at the horizon (holds do not count,
    ``Task.step``), but never under an operator's hands: a timeout during a takeover waits for the
    hand-back (or, in the fleet, the lease's end)."""
    return frame.done and (frame.success or mode != Mode.TELEOP)


class Controller:
    """Batched control of the robots of one policy, keyed by robot id.

    signals: name -> calibrated or shadow ``AssistanceSignal``; asking: the one whose decision asks
    for help and returns control (None: evaluation, nothing asks); action_space: turns operator
    commands into absolute targets; inference: where the batched network calls run (``policy.inference``;
    default: here, on ``policy`` and ``signals``).
    """

    def __init__(
        self,
        policy: DiffusionPolicy,
        signals: Mapping[str, AssistanceSignal],
        asking: str | None,
        action_space: ActionSpace,
        config: ControllerConfig | None = None,
        inference: Inference | None = None,
        seed: int = 0,
    ) -> None:
        if asking is not None:
            if asking not in signals:
                raise SignalError(f"the asking signal {asking!r} is not among the controller's signals")
            signals[asking].threshold  # noqa: B018 - raises SignalError when it is not calibrated
        self.policy = policy
        self.signals = dict(signals)
        self.asking = asking
        self.action_space = action_space
        self.config = config or ControllerConfig()
        self.seed = seed  # with each episode's seed, the seed of its sampling noise
        self.inference = inference if inference is not None else LocalInference(policy, self.signals)
        # CPU seconds the inference back end spent so far, per part ("policy", each signal): what a tick's
        # network calls cost apart from the rest of the loop (``hitl bench fleet`` reports it)
        self.inference_cpu_s: dict[str, float] = {}
        self._robots: dict[int, _Robot] = {}

    # -- robots ---------------------------------------------------------------------------------------
    def reset(self, robot_id: int, seed: int, control: RobotControl | None = None) -> None:
        """A new episode: empty history and queue, autonomous, the signals forget the robot, and its
        sampling noise restarts from (controller seed, ``seed``). control: the robot's control state
        (the fleet keeps one per robot across episodes and policy versions; default: a new one)."""
        state = np.random.SeedSequence([self.seed, int(seed)]).generate_state(2, np.uint32)
        g = torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))
        control = control if control is not None else RobotControl()
        control.new_episode()
        self._robots[robot_id] = _Robot(g, control)
        self.inference.reset([robot_id])

    def remove(self, robot_id: int) -> None:
        """Forgets a robot (it moved to another controller, or left the fleet)."""
        if self._robots.pop(robot_id, None) is not None:
            self.inference.reset([robot_id])

    def __contains__(self, robot_id: int) -> bool:
        return robot_id in self._robots

    def control(self, robot_id: int) -> RobotControl:
        """The robot's control state: its mode and counters (``policy.hitl_state``)."""
        return self._robot(robot_id).control

    def mode(self, robot_id: int) -> Mode:
        return self._robot(robot_id).control.mode

    def ask(self, robot_id: int, hold: np.ndarray) -> None:
        """Puts a robot in ``waiting`` as if it had asked: it holds ``hold`` (10,)."""
        r = self._robot(robot_id)
        r.control.ask(hold)
        r.queue.clear()

    def take_over(self, robot_id: int) -> None:
        """An operator takes control; in budgeted mode the budget starts now."""
        r = self._robot(robot_id)
        if r.control.mode != Mode.TELEOP:
            r.control.take_over(self.config.budget if self.config.hand_back == "budgeted" else None)
            r.queue.clear()

    def release(self, robot_id: int) -> None:
        """Control goes back to the policy, which samples a fresh chunk at the next frame, from a fresh
        history (``resume = "restart"``) or the one the takeover's frames left (``"history"``), and does
        not ask again for ``config.cooldown`` steps."""
        r = self._robot(robot_id)
        r.control.hand_back(self.config.cooldown)
        if self.config.resume == "restart":
            r.history.clear()
        r.queue.clear()

    def _robot(self, robot_id: int) -> _Robot:
        try:
            return self._robots[robot_id]
        except KeyError:
            raise KeyError(f"robot {robot_id} has no episode in this controller (call reset first)") from None

    # -- the step ---------------------------------------------------------------------------------------
    def step(
        self,
        frames: Mapping[int, RobotFrame],
        commands: Mapping[int, TeleopCommand] | None = None,
        send: ActionSink | None = None,
    ) -> dict[int, RobotStep]:
        """One control step for the robots in ``frames`` (each frame new since the robot's last step).

        commands: robot id -> the operator command to apply now (robots under teleop only); send:
        called with (robot id, action, source) as soon as an action is known, operator and hold
        actions before the policy's batch is computed.
        """
        commands = commands or {}
        out: dict[int, RobotStep] = {}
        scored: list[int] = []
        cameras = [c.name for c in self.policy.config.cameras]
        for rid, frame in frames.items():
            r = self._robot(rid)
            obs = torch.as_tensor(frame.obs, dtype=torch.float32)
            if lacks := [c for c in cameras if c not in frame.images]:
                raise ValueError(
                    f"robot {rid}'s frame has no image of camera(s) {lacks} its policy sees: make its task with "
                    "images=True (sim.registry.make_task)"
                )
            seen = (obs, {c: frame.images[c] for c in cameras})
            if not r.history:
                r.history.extend([seen] * self.policy.config.obs_horizon)
            else:
                r.history.append(seen)
                while len(r.history) > self.policy.config.obs_horizon:
                    r.history.popleft()
            cmd = commands.get(rid)
            mode = r.control.mode
            if cmd is not None and mode != Mode.TELEOP:
                raise ValueError(f"robot {rid} is {mode}, not under teleop: it takes no operator command")
            if mode == Mode.TELEOP and cmd is not None:
                target = self.action_space.apply_teleop(cmd, frame.pos, frame.rot)
                r.control.drive(target.action)
                out[rid] = RobotStep(rid, target.action, keys.SOURCE_OPERATOR, mode, command=cmd, target=target)
                scored.append(rid)
            elif mode == Mode.AUTONOMOUS:
                scored.append(rid)
                continue
            else:  # waiting, or teleop with no command this step
                hold = r.control.hold if r.control.hold is not None else frame.hold
                out[rid] = RobotStep(rid, np.asarray(hold, np.float64).copy(), keys.SOURCE_HOLD, mode)
            if send is not None:
                send(rid, out[rid].action, out[rid].source)
        if scored and self.config.batch_invariant:
            for rid in scored:
                self._score_and_decide([rid], frames, out, send)
        elif scored:
            self._score_and_decide(scored, frames, out, send)
        return {rid: out[rid] for rid in frames}

    def _asks(self, c: RobotControl, frame: RobotFrame, signal_wants: bool, urgent: bool = False) -> str | None:
        """Who makes an autonomous robot ask now: its signal, or the watchdog (once per episode, when
        the robot has used ``watchdog`` of its horizon); None in shadow runs, and while a cooldown runs
        unless the signal's request is ``urgent`` (the policy's next step would undo a takeover)."""
        if not self.config.assistance:
            return None
        if signal_wants and urgent:
            return self.asking
        if c.cooldown > 0:
            return None
        if signal_wants:
            return self.asking
        late = (
            self.config.watchdog is not None
            and frame.horizon > 0
            and frame.clock >= self.config.watchdog * frame.horizon
        )
        if late and not c.watched and not frame.success:
            c.watchdog_fired()
            return WATCHDOG
        return None

    def _score_and_decide(
        self, ids: list[int], frames: Mapping[int, RobotFrame], out: dict[int, RobotStep], send: ActionSink | None
    ) -> None:
        cfg = self.policy.config
        robots = [self._robots[i] for i in ids]
        obs = torch.stack([torch.stack([o for o, _ in r.history]) for r in robots])
        images = {  # camera -> (B, H, size, size, 3) uint8
            c.name: torch.as_tensor(np.stack([np.stack([im[c.name] for _, im in r.history]) for r in robots]))
            for c in cfg.cameras
        }
        current = torch.as_tensor(np.stack([frames[i].hold for i in ids]), dtype=torch.float32)
        controls = [r.control for r in robots]
        teleop = np.array([c.mode == Mode.TELEOP for c in controls])
        # a fresh chunk for robots with nothing queued (and the would-be chunk of teleoperated robots)
        need = [j for j, r in enumerate(robots) if not r.queue]
        plans = torch.empty((len(ids), cfg.action_horizon, ACTION_DIM))
        for j, r in enumerate(robots):  # the plan a queued robot is executing, from the action it takes now
            if j not in need:
                rest = list(r.queue)
                rest += [rest[-1]] * (cfg.action_horizon - len(rest))
                plans[j] = torch.as_tensor(np.stack(rest[: cfg.action_horizon]), dtype=torch.float32)
        noise = None
        if need:
            noise = torch.stack(
                [torch.randn((cfg.action_horizon, ACTION_DIM), generator=robots[j].generator) for j in need]
            )
        operator = None
        if teleop.any():
            operator = torch.full((len(ids), ACTION_DIM), float("nan"))
            for j in np.flatnonzero(teleop):
                operator[j] = torch.as_tensor(out[ids[j]].action, dtype=torch.float32)
        asks = self.asking if self.asking is not None and self.config.assistance else None
        request = InferenceRequest(
            obs,
            current,
            np.asarray(ids),
            need,
            noise,
            plans,
            teleop,
            operator,
            asks,
            engaged=np.array([c.engaged for c in controls]),
            agreed=np.array([np.nan if c.agreed is None else float(c.agreed) for c in controls]),
            after_takeover=np.array([c.driven for c in controls]),
            images=images or None,
        )
        try:
            result = self.inference.run(request)
        except InferenceUnavailable as exc:
            self._hold_without_inference(ids, robots, frames, out, send, teleop, str(exc))
            return
        for part, seconds in result.cpu_s.items():
            self.inference_cpu_s[part] = self.inference_cpu_s.get(part, 0.0) + seconds
        for j in need:
            if not teleop[j]:
                robots[j].queue.extend(result.plans[j, : cfg.n_action_steps].numpy().astype(np.float64))
        scores, wants = result.scores, result.wants
        asking = wants.get(asks) if asks is not None else None
        urgent = result.urgent if asking is not None else None
        agrees = scores[asks].parts.get(AGREES) if asking is not None else None
        field = next((sc.detail for sc in scores.values() if isinstance(sc.detail, UncertaintyBatch)), None)
        for j, (rid, r) in enumerate(zip(ids, robots, strict=True)):
            frame, c = frames[rid], r.control
            if teleop[j]:
                step = out[rid]
                still = bool(asking[j]) if asking is not None else None
                agreed = bool(agrees[j] > 0) if agrees is not None and np.isfinite(agrees[j]) else None
                self._count_operator_step(rid, r, step, True, still, agreed)
            else:
                wanted = asking is not None and bool(asking[j])
                c.policy_step(wanted if asking is not None else None)
                by = self._asks(c, frame, wanted, urgent is not None and bool(urgent[j]))
                if by is not None:
                    self.ask(rid, frame.hold)
                    step = RobotStep(rid, c.hold.copy(), keys.SOURCE_HOLD, c.mode, asked=True, asked_by=by)
                    step.why = result.why.get(j) if by == asks else None
                else:
                    c.count_down()
                    step = RobotStep(rid, r.queue.popleft(), keys.SOURCE_POLICY, c.mode)
            step.mode = c.mode
            step.obs, step.current = obs[j].numpy(), current[j].numpy()
            step.seen = result.seen[j].numpy() if result.seen is not None else step.obs
            step.scores = {name: float(sc.value[j]) for name, sc in scores.items()}
            step.wants = {name: bool(w[j]) for name, w in wants.items()}
            step.uncertainty = field.robot(j) if field is not None else None
            out[rid] = step
            if send is not None and not teleop[j]:
                send(rid, step.action, step.source)

    def _count_operator_step(
        self,
        rid: int,
        r: _Robot,
        step: RobotStep,
        scored: bool,
        still: bool | None = None,
        agreed: bool | None = None,
    ) -> None:
        """An operator step (``scored``: the signals scored it; ``still`` / ``agreed``: the asking signal's
        decision and the policy's agreement on it, None when not known): the control state counts it, and
        control goes back when the budget, or the calm run of ``return_after``, is used up."""
        if r.control.operator_step(scored, still, agreed, self.config.return_after):
            self.release(rid)
            step.returned = True

    def _hold_without_inference(
        self,
        ids: list[int],
        robots: list[_Robot],
        frames: Mapping[int, RobotFrame],
        out: dict[int, RobotStep],
        send: ActionSink | None,
        teleop: np.ndarray,
        why: str,
    ) -> None:
        """The back end could not answer: the robots the policy drives hold where they are (their
        queues wait, nothing is scored), operators' steps count as usual."""
        for j, (rid, r) in enumerate(zip(ids, robots, strict=True)):
            if teleop[j]:
                step = out[rid]
                self._count_operator_step(rid, r, step, False)
            else:
                step = RobotStep(rid, np.asarray(frames[rid].hold, np.float64).copy(), keys.SOURCE_HOLD, r.control.mode)
                if send is not None:
                    send(rid, step.action, step.source)
            step.mode, step.unavailable = r.control.mode, why
            out[rid] = step

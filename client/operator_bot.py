"""The simulated operator as an API client: it watches the queue, claims the most urgent robot,
drives it with the task's scripted expert from the operator view, and hands back.

It drives as the in-process simulated operator does (``lab.assisted.ExpertOperator``): the expert
tries again when a grasp fails (``Expert.retry``), and it gives up, handing back, once the episode
has run ``OVERTIME`` horizons of its clock, where the in-process episodes stop (``policy.lockstep``).

It uses only the public REST API, so it is also an example client for users.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass

import httpx
import numpy as np

from policy.lockstep import OVERTIME
from sim.experts import OperatorStyle
from sim.registry import make_expert
from sim.spaces import TeleopLimits
from sim.view import OperatorView, ViewUnavailable

log = logging.getLogger("hitl.operator_bot")
LIMITS = TeleopLimits()


def overtime(view: dict) -> bool:
    """Whether the episode's clock has run ``OVERTIME`` horizons: there the simulated operator gives up
    and hands back, as the in-process one's episodes stop (``policy.lockstep``), and the episode, past
    its horizon, ends as a timeout at the hand-back.

    The clock, not the steps: in the fleet a request waits in the queue while the one operator drives
    another robot, and those holds (which the in-process operator, answering at once, never has) do not
    use up the episode. Counting them gave up, without a command, on every robot that had waited 30 s
    for its turn, and such a robot, asking again, was given up on again until its clock ran out."""
    clock, horizon = view.get("clock"), view.get("horizon")
    return isinstance(clock, int) and isinstance(horizon, int) and horizon > 0 and clock >= OVERTIME * horizon


@dataclass(frozen=True)
class HumanPace:
    """What a person needs that a script does not, in seconds (``hitl bench operators`` gives them in
    control ticks): claim_s, from seeing a request at the head of the queue to claiming it; switch_s,
    more when the robot is not the one served last (finding it, reading its scene); min_takeover_s, the
    least time a takeover occupies the operator, from the claim on, however soon the robot is handed
    back (Fleet-DAgger's minimum intervention time, counted on the operator's side: the service, not the
    operator, decides the hand-back here)."""

    claim_s: float = 0.0
    switch_s: float = 0.0
    min_takeover_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("claim_s", "switch_s", "min_takeover_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")


class TakeoverOver(Exception):
    """The takeover cannot go on: the service handed control back, the episode ended, or the robot is gone."""


class OperatorBot:
    """Serves the assistance queue. Survives every state the API can return: a robot that is handed
    back, reset, paused, faulted or whose episode ends mid-takeover ends that takeover; network errors
    and server errors are logged and retried with backoff."""

    def __init__(
        self,
        url: str,
        token: str,
        heartbeat_s: float = 1.0,
        timeout: float = 10.0,
        hands_back_when_held: bool = False,
        style: OperatorStyle | str = OperatorStyle.CARRY_ON,
        pace: HumanPace | None = None,
    ) -> None:
        """hands_back_when_held: release a robot once the object it was asked about is held (``Expert.holding``;
        as ``lab.assisted.ExpertOperator`` does with it), instead of driving until the service hands back;
        style: how it plans at each request (``sim.experts.OperatorStyle``); pace: a person's delays (default:
        none, the bot answers at once)."""
        self.api = url.rstrip("/") + "/api/v1"
        self.style = OperatorStyle(style)
        self.hands_back_when_held = hands_back_when_held
        self.client = httpx.Client(headers={"Authorization": f"Bearer {token}"}, timeout=timeout)
        self.heartbeat_s = heartbeat_s
        self.pace = pace or HumanPace()
        self.busy_s = 0.0  # time spent on requests: the delays, the takeovers and the rest of each minimum
        self._serving_since: float | None = None  # when the request in progress began (None: idle)
        self.last_robot: int | None = None
        self.takeovers = 0
        self.commands = 0
        self.errors = 0  # network errors and unexpected answers, each logged
        self.waits: list[tuple[int, float]] = []  # (robot id, claim's waiting_s): how long its request waited
        self._driving: dict[int, list] = {}  # robot id -> [episode seed, expert, clock after its last command]

    def close(self) -> None:
        self.client.close()

    def _get(self, path: str):
        r = self.client.get(self.api + path)
        if r.status_code in (404, 409):
            raise TakeoverOver(f"GET {path}: {r.status_code} {r.text}")
        r.raise_for_status()
        return r.json()

    def _view(self, robot_id: int, raw: dict | None = None) -> OperatorView:
        """The operator view of ``robot_id`` (``raw``: its JSON, when already fetched); TakeoverOver when
        it has no scene to drive."""
        try:
            return OperatorView.from_api(raw if raw is not None else self._get(f"/robots/{robot_id}/view"))
        except ViewUnavailable as why:
            raise TakeoverOver(str(why)) from None

    def next_request(self) -> dict | None:
        return next((r for r in self._get("/assistance") if r["holder"] is None), None)

    def takeover(self, robot_id: int, seed: int = 0, max_steps: int = 1000) -> int:
        """Claims ``robot_id`` and drives it until the service hands control back; returns steps driven.
        ``seed`` seeds the plan only when the service does not report the episode's seed."""
        r = self.client.post(f"{self.api}/robots/{robot_id}/claim")
        if r.status_code in (404, 409):  # someone else was faster, or the request is gone
            return 0
        r.raise_for_status()
        with contextlib.suppress(ValueError, KeyError, TypeError):  # an answer without its wait: drive anyway
            self.waits.append((robot_id, float(r.json()["waiting_s"])))
        steps = 0
        try:
            self._wait_claimed(robot_id)
            raw = self._get(f"/robots/{robot_id}/view")
            view = self._view(robot_id, raw)
            expert = self._expert_for(robot_id, view, raw, seed)
            held_at_start = expert.holding(view)
            last_beat = time.monotonic()
            body = None  # a command refused with 429 is sent again, not recomputed (the expert has a state)
            while steps < max_steps:
                detail = self._get(f"/robots/{robot_id}")
                if detail["mode"] == "paused":  # an admin stopped it: let someone else have it later
                    self.client.post(f"{self.api}/robots/{robot_id}/release")
                    break
                if detail["mode"] != "teleop":
                    break
                if body is None:
                    raw = self._get(f"/robots/{robot_id}/view")
                    view = self._view(robot_id, raw)
                    if overtime(raw):
                        log.info("robot %d: clock %d of its episode, giving up", robot_id, raw["clock"])
                        self.client.post(f"{self.api}/robots/{robot_id}/release")
                        break
                    if self.hands_back_when_held and not held_at_start and expert.holding(view):
                        log.info("robot %d: object held after %d steps, handing back", robot_id, steps)
                        self.client.post(f"{self.api}/robots/{robot_id}/release")
                        break
                    # send what the robot will execute, in the command's wire form (the API's body)
                    body = expert.act(view).clamped(LIMITS).to_dict()
                r = self.client.post(f"{self.api}/robots/{robot_id}/command", json=body)
                if r.status_code in (404, 409):  # lease lost, control handed back, episode over
                    break
                if r.status_code == 429:  # the next step is full: let a tick apply it, then send it again
                    time.sleep(0.02)
                    continue
                r.raise_for_status()
                body = None
                self.commands += 1
                steps += 1
                clock = raw.get("clock")
                if robot_id in self._driving and clock is not None:
                    self._driving[robot_id][2] = clock + 1  # where the robot stands once this step is done
                self._wait_applied(robot_id, detail["assisted_steps"], clock)
                if time.monotonic() - last_beat > self.heartbeat_s:
                    self.client.post(f"{self.api}/robots/{robot_id}/heartbeat")
                    last_beat = time.monotonic()
            else:  # gave up: hand the robot back now rather than let the lease run out
                log.info("robot %d: no success after %d steps, handing back", robot_id, steps)
                self.client.post(f"{self.api}/robots/{robot_id}/release")
        except TakeoverOver as why:
            log.info("robot %d: takeover over (%s)", robot_id, why)
        finally:
            self.takeovers += 1
        return steps

    def _serve(self, robot_id: int, stop=None) -> int:
        """One request at the pace of a person: the delays before the claim, the takeover, and the rest of
        the minimum takeover time; the time it all took counts as busy (``busy_at``). ``stop()`` true after
        the delays: no claim."""
        started = self._serving_since = time.monotonic()
        try:
            delay = self.pace.claim_s + (self.pace.switch_s if robot_id != self.last_robot else 0.0)
            if delay:
                time.sleep(delay)
            if stop is not None and stop():
                return 0
            claimed = time.monotonic()
            steps = self.takeover(robot_id, seed=self.takeovers)
            if steps:
                self.last_robot = robot_id
                rest = self.pace.min_takeover_s - (time.monotonic() - claimed)
                if rest > 0:
                    time.sleep(rest)
            return steps
        finally:
            self.busy_s += time.monotonic() - started
            self._serving_since = None

    def busy_at(self, now: float) -> float:
        """Seconds busy up to ``now`` (``time.monotonic``), the request in progress counted so far."""
        since = self._serving_since
        return self.busy_s + (max(0.0, now - since) if since is not None else 0.0)

    def _expert_for(self, robot_id: int, task: OperatorView, raw: dict, seed: int):
        """The expert driving this robot, as the in-process simulated operator has it
        (``lab.assisted.ExpertOperator``): one per episode, re-planned at each request from the view,
        in its style (``Expert.take_over``: episode seed, requests so far), carrying on with
        its plan when nothing moved the robot since its last command (the robot's clock is where that
        command left it)."""
        episode = raw.get("episode_seed")
        if episode is None:  # a service that does not report its episodes: a fresh plan per takeover
            expert = make_expert(task.name, retry=True)
            expert.resume(task, np.random.default_rng([seed, robot_id]))
            return expert
        if self._driving.get(robot_id, [None])[0] != episode:
            self._driving[robot_id] = [episode, make_expert(task.name, retry=True, style=self.style), None]
        _, expert, left_at = self._driving[robot_id]
        carry_on = left_at is not None and left_at == raw.get("clock")
        expert.take_over(task, int(episode), int(raw.get("events") or 0), carry_on)
        return expert

    def _wait_claimed(self, robot_id: int, timeout: float = 5.0) -> None:
        """Until the service's next control tick has put the claimed robot under control: it shows
        ``waiting`` until then (or for good, when the claim came too late)."""
        deadline = time.monotonic() + timeout
        while self._get(f"/robots/{robot_id}")["mode"] == "waiting" and time.monotonic() < deadline:
            time.sleep(0.01)

    def _wait_applied(self, robot_id: int, before: int, clock: int | None, timeout: float = 5.0) -> None:
        """Until the step of the command just sent is done: the robot's clock moved past ``clock`` (or,
        from a service that reports no clock, its assisted steps moved), or it left teleop."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if clock is not None:
                v = self._get(f"/robots/{robot_id}/view")
                if v["mode"] != "teleop" or (v.get("clock") is not None and v["clock"] > clock):
                    return
            else:
                d = self._get(f"/robots/{robot_id}")
                if d["assisted_steps"] != before or d["mode"] != "teleop":
                    return
            time.sleep(0.01)

    def run(self, max_takeovers: int | None = None, idle_sleep: float = 0.2, stop=None) -> None:
        """Serves the queue until ``max_takeovers`` or ``stop()`` returns True."""
        backoff = idle_sleep
        while (max_takeovers is None or self.takeovers < max_takeovers) and not (stop and stop()):
            try:
                req = self.next_request()
                if req is None:
                    time.sleep(idle_sleep)
                    continue
                steps = self._serve(req["robot_id"], stop)
                log.info("robot %d: drove %d steps", req["robot_id"], steps)
                backoff = idle_sleep
            except (httpx.HTTPError, TakeoverOver, KeyError, TypeError, ValueError) as exc:
                # the service restarting, a server error, an answer of an unexpected shape: keep serving
                self.errors += 1
                log.warning("operator bot: %s: %s (retrying in %.1f s)", type(exc).__name__, exc, backoff)
                time.sleep(backoff)
                backoff = min(10.0, backoff * 2)

"""One robot's human-in-the-loop state: its mode and counters, and the hand-back rule's transitions.

``RobotControl`` is the one record of where a robot stands between its policy and its operator: the mode
(``Mode``), the pose it holds while it waits, the operator steps left in a budgeted request, the run of
operator steps on which the policy no longer wants help (``return_after``), the cooldown after a
hand-back, whether the watchdog asked this episode, and the facts the asking signal's trigger reads
about takeovers (``engaged``, ``agreed``, ``driven``; ``policy.signals.base.TriggerState``). Nothing
else keeps a copy: the controller (``policy.controller``) changes it in its step, the fleet
(``server.fleet``) in its tick, and both read it.

Every change is a method here. ``bind_writer`` pins the thread allowed to call them (the fleet's control
loop); a change from any other thread raises ``WrongWriter``, so claims, releases and admin actions reach
a served robot only through the loop's inbox (``server.fleet.inbox``).
"""

from __future__ import annotations

import threading
from enum import StrEnum

import numpy as np


class Mode(StrEnum):
    """``autonomous -> waiting -> teleop -> autonomous`` is the controller's cycle; the fleet adds
    ``paused`` (an admin's: not stepped, the scene and clock frozen), ``done`` (the episode ended; the
    next starts at once) and ``faulted`` (the worker died; it restarts with backoff). A ``StrEnum``: it
    compares equal to its value, which the API and the console show."""

    AUTONOMOUS = "autonomous"
    WAITING = "waiting"
    TELEOP = "teleop"
    PAUSED = "paused"
    DONE = "done"
    FAULTED = "faulted"


MODES = tuple(Mode)
RESUMABLE = (Mode.WAITING, Mode.TELEOP)  # what a paused robot resumes into; anything else resumes autonomous


class WrongWriter(RuntimeError):
    """A robot's control state was changed from a thread other than the one bound to write it."""


class RobotControl:
    """One robot's mode and counters (see the module). Read the properties; change it through the methods.

    hold: (10,) the action that holds the pose the robot asked at (None unless it waits or is driven);
    teleop_left: operator steps left in a budgeted request (None: not under teleop, or continuous);
    calm: consecutive operator steps on which the asking signal no longer wanted help; cooldown: policy
    steps left on which the robot does not ask (after a hand-back); watched: the watchdog asked this
    episode; engaged: the asking signal wanted help and no operator step has settled it since; agreed:
    whether the policy agreed with the operator's last step (None: no operator step since the robot's
    last policy step, or the signal does not score agreement); driven: an operator drove the robot
    since its last policy step."""

    __slots__ = (
        "_mode",
        "_paused_from",
        "_hold",
        "_teleop_left",
        "_calm",
        "_cooldown",
        "_watched",
        "_engaged",
        "_agreed",
        "_driven",
        "_writer",
    )

    def __init__(self) -> None:
        self._writer: int | None = None
        self._mode, self._paused_from = Mode.AUTONOMOUS, None
        self._clear_episode()

    # -- reading ----------------------------------------------------------------------------------------
    mode = property(lambda self: self._mode)
    paused_from = property(lambda self: self._paused_from, doc="the mode a paused robot resumes into")
    hold = property(lambda self: self._hold)
    teleop_left = property(lambda self: self._teleop_left)
    calm = property(lambda self: self._calm)
    cooldown = property(lambda self: self._cooldown)
    watched = property(lambda self: self._watched)
    engaged = property(lambda self: self._engaged)
    agreed = property(lambda self: self._agreed)
    driven = property(lambda self: self._driven)

    @property
    def stepped_mode(self) -> Mode:
        """The controller's mode of the robot: the one a pause will resume into, else the mode."""
        return self._paused_from if self._mode == Mode.PAUSED and self._paused_from is not None else self._mode

    def __repr__(self) -> str:
        return f"RobotControl(mode={self._mode}, teleop_left={self._teleop_left}, cooldown={self._cooldown})"

    # -- who writes ---------------------------------------------------------------------------------------
    def bind_writer(self, thread: threading.Thread | None) -> None:
        """Only ``thread`` may change this state from now on (None: any thread, as in-process evaluation)."""
        self._writer = thread.ident if thread is not None else None

    def _check(self) -> None:
        if self._writer is not None and threading.get_ident() != self._writer:
            raise WrongWriter(
                f"a robot's control state is written by its control loop only (thread {self._writer}); "
                f"thread {threading.get_ident()} tried to change it"
            )

    def _clear_episode(self) -> None:
        self._hold: np.ndarray | None = None
        self._teleop_left: int | None = None
        self._calm = 0
        self._cooldown = 0
        self._watched = False
        self._engaged = False
        self._agreed: bool | None = None
        self._driven = False

    def _enter(self, mode: Mode) -> None:
        """A transition of the controller's cycle: on a paused robot it becomes the mode the pause resumes into."""
        if self._mode == Mode.PAUSED:
            self._paused_from = mode
        else:
            self._mode = mode

    # -- the controller's cycle ---------------------------------------------------------------------------
    def new_episode(self) -> None:
        """A new episode: autonomous (a pause holds on), every counter cleared."""
        self._check()
        self._clear_episode()
        if self._mode == Mode.PAUSED:
            self._paused_from = Mode.AUTONOMOUS
        else:
            self._mode = Mode.AUTONOMOUS

    def ask(self, hold: np.ndarray) -> None:
        """The robot asks for help: it waits, holding ``hold`` (10,)."""
        self._check()
        self._enter(Mode.WAITING)
        self._hold, self._teleop_left, self._calm = np.asarray(hold, np.float64).copy(), None, 0

    def take_over(self, budget: int | None) -> None:
        """An operator takes control (``budget``: operator steps before a budgeted hand-back; None: continuous)."""
        self._check()
        if self.stepped_mode != Mode.TELEOP:
            self._enter(Mode.TELEOP)
            self._calm, self._teleop_left = 0, budget

    def hand_back(self, cooldown: int) -> None:
        """Control goes back to the policy, which does not ask again for ``cooldown`` of its steps."""
        self._check()
        self._enter(Mode.AUTONOMOUS)
        self._hold, self._teleop_left, self._calm, self._cooldown = None, None, 0, cooldown

    def drive(self, target: np.ndarray) -> None:
        """An operator's command became ``target`` (10,): the robot holds it until the next command."""
        self._check()
        self._hold = np.asarray(target, np.float64).copy()

    def operator_step(
        self, scored: bool, still_wants: bool | None, agrees: bool | None, return_after: int | None
    ) -> bool:
        """An operator step was taken (``scored``: the signals scored it): the budget counts it,
        ``still_wants`` (the asking signal's decision on it; None: none) extends or breaks the calm run,
        ``agrees`` (the policy's agreement with it; None: not scored) is kept for the next policy step.
        Returns whether control goes back now: the budget is used up, or the calm run reached
        ``return_after``."""
        self._check()
        self._driven = self._driven or scored
        if still_wants is not None and return_after is not None:
            self._calm = self._calm + 1 if not still_wants else 0
        if agrees is not None:
            self._agreed = agrees
        if self._teleop_left is not None:
            self._teleop_left -= 1
        used_up = self._teleop_left is not None and self._teleop_left <= 0
        return used_up or (return_after is not None and self._calm >= return_after)

    def policy_step(self, wanted: bool | None) -> None:
        """The robot was scored on a policy step on which the asking signal decided ``wanted`` (None: no
        asking signal): the takeover facts of the step are used up, and a request stays engaged until a
        step the policy agreed on settles it (``TriggerState``)."""
        self._check()
        if wanted is not None:
            self._engaged = bool(wanted) or (self._engaged and self._agreed is None)
        self._agreed, self._driven = None, False

    def count_down(self) -> None:
        """The policy acted without asking: one step less of the cooldown."""
        self._check()
        self._cooldown = max(0, self._cooldown - 1)

    def watchdog_fired(self) -> None:
        self._check()
        self._watched = True

    # -- the fleet's ---------------------------------------------------------------------------------------
    def pause(self) -> None:
        """An admin's pause: not stepped until ``resume``."""
        self._check()
        if self._mode != Mode.PAUSED:
            self._paused_from, self._mode = self._mode, Mode.PAUSED

    def resume(self) -> Mode:
        """Ends a pause: back to the mode it left (``RESUMABLE``), else autonomous; returns that mode."""
        self._check()
        back = self._paused_from if self._paused_from in RESUMABLE else Mode.AUTONOMOUS
        self._mode, self._paused_from = back, None
        return back

    def episode_ended(self) -> None:
        """The episode ended on its own; the next one starts (``new_episode``)."""
        self._check()
        self._enter(Mode.DONE)

    def fault(self) -> None:
        """The robot's worker died (a fault ends a pause)."""
        self._check()
        self._mode, self._paused_from = Mode.FAULTED, None
        self._clear_episode()

    def restart(self) -> None:
        """A faulted robot's worker restarts: autonomous again."""
        self._check()
        self._mode, self._paused_from = Mode.AUTONOMOUS, None

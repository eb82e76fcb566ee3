"""One robot's inbox: what the API and the console ask of a robot, waiting for the control loop's next tick.

The control loop is the one writer of a robot's control state (``policy.hitl_state.RobotControl``). So
nothing an API call asks changes a robot at once: a claim, a hand-back or an admin's pause, resume,
reset or request for help is put here, and the loop applies them in order at the start of its next
tick (``Lifecycle.apply_inbox``), before it steps anyone; operator commands wait here too, composed
(``server.fleet.commands``), and the tick that steps the robot applies them.

Claims and releases are decided in the assistance queue under its own lock (who holds the robot, the
lease); a claimant's commands are accepted from then on, and wait for the tick that applies the claim.
While the loop runs the call waits for that tick (``HANDOVER_WAIT_S`` at most: a tick in progress is not
cut short), so a claimant who is answered sees the robot under teleop. An admin's action waits for the
tick that applies it, and gets its answer or its error from there (``Ticket``); with no loop running
(before the service starts, or a test that drives ticks by hand) the caller applies the inbox itself,
under the fleet lock. A claim or release made with no loop running is applied by the next tick.

A handover is applied only if the queue still agrees when the tick comes: a claim whose request has
ended (the episode ended, the robot was reset) or whose lease has run out in between changes nothing,
as if it had come a moment later.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from server.errors import ServiceError
from server.fleet.commands import CommandMailbox
from sim.spaces import TeleopCommand, TeleopLimits

ADMIN_WAIT_S = 10.0  # how long an admin's action waits for the tick that applies it
HANDOVER_WAIT_S = 2.0  # how long a claim or a release waits for it (then answers; the next tick applies it)


@dataclass(frozen=True)
class Handover:
    """A claim or a release the queue has decided; ``applied`` is set once a tick has looked at it."""

    kind: Literal["claim", "release"]
    operator: str
    applied: threading.Event = field(default_factory=threading.Event, compare=False, repr=False)

    def wait(self, timeout: float = HANDOVER_WAIT_S) -> bool:
        """Whether a tick applied it within ``timeout`` (the lease is held either way)."""
        return self.applied.wait(timeout)


@dataclass
class Ticket:
    """An admin's action (``run``, called by the loop with the robot) and its answer, once applied."""

    run: Callable[[], object]
    done: threading.Event = field(default_factory=threading.Event)
    result: object = None
    error: BaseException | None = None

    def apply(self) -> None:
        try:
            self.result = self.run()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller, who raises it
            self.error = exc
        finally:
            self.done.set()

    def answer(self, timeout: float = ADMIN_WAIT_S) -> object:
        if not self.done.wait(timeout):
            raise ServiceError(503, f"the control loop did not apply the action within {timeout:g} s")
        if self.error is not None:
            raise self.error
        return self.result


Item = Handover | Ticket


class Inbox:
    """One robot's handovers, admin actions and operator commands, in order (thread-safe)."""

    def __init__(self, limits: TeleopLimits) -> None:
        self._lock = threading.Lock()
        self._items: list[Item] = []
        self._commands = CommandMailbox(limits)

    # -- the API's side ---------------------------------------------------------------------------------
    def put(self, item: Item) -> None:
        with self._lock:
            self._items.append(item)

    def command(self, command: TeleopCommand) -> int:
        """Accepts ``command`` for the tick that next steps the robot; returns how many that tick applies
        (429 past the per-step limits: ``server.fleet.commands``)."""
        return self._commands.put(command)

    # -- the loop's side --------------------------------------------------------------------------------
    def take(self) -> list[Item]:
        """The handovers and actions waiting, in order; the inbox keeps none of them."""
        with self._lock:
            items, self._items = self._items, []
        return items

    def take_command(self) -> tuple[TeleopCommand, float, int] | None:
        """(the composed command, when its first part arrived, how many), and no command waits any more."""
        return self._commands.take()

    def drop_commands(self) -> None:
        """The commands waiting are never applied (control changed hands, the episode ended)."""
        self._commands.clear()

    @property
    def commands_waiting(self) -> int:
        return self._commands.count

"""A fleet robot's mode: the controller's three (``policy.controller.Mode``) and the fleet's own three.

``autonomous -> waiting -> teleop -> autonomous`` come from the controller; the fleet adds ``paused``
(not stepped: the scene and the episode clock are frozen), ``done`` (the episode ended; the next one
starts at once) and ``faulted`` (the worker died; it is restarted with backoff). A ``StrEnum``: it
compares equal to its value, and the API and the console show that value.
"""

from __future__ import annotations

from enum import StrEnum

from policy.controller import Mode


class FleetMode(StrEnum):
    AUTONOMOUS = Mode.AUTONOMOUS.value
    WAITING = Mode.WAITING.value
    TELEOP = Mode.TELEOP.value
    PAUSED = "paused"
    DONE = "done"
    FAULTED = "faulted"

    @classmethod
    def of(cls, mode: Mode) -> FleetMode:
        """The fleet's name for a controller mode."""
        return cls(mode.value)


MODES = tuple(FleetMode)

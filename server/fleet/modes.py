"""A fleet robot's mode: the controller's three (``policy.controller.Mode``) and the fleet's own three.

``autonomous -> waiting -> teleop -> autonomous`` come from the controller; the fleet adds ``paused``
(not stepped: the scene and the episode clock are frozen), ``done`` (the episode ended; the next one
starts at once) and ``faulted`` (the worker died; it is restarted with backoff). A ``StrEnum``: it
compares equal to its value, and the API and the console show that value.
"""

from __future__ import annotations

from enum import StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # no torch to read a mode (tests/server/fleet/test_robot.py checks the values agree)
    from policy.controller import Mode


class FleetMode(StrEnum):
    AUTONOMOUS = "autonomous"  # the controller's three (``policy.controller.Mode``)
    WAITING = "waiting"
    TELEOP = "teleop"
    PAUSED = "paused"
    DONE = "done"
    FAULTED = "faulted"

    @classmethod
    def of(cls, mode: Mode) -> FleetMode:
        """The fleet's name for a controller mode."""
        return cls(mode.value)


MODES = tuple(FleetMode)

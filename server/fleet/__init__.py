"""The fleet: simulated or real robots driven by their policies' one control step, helped by operators.

``Fleet`` (``server.fleet.fleet``) puts the parts together and is what the API and the console use, through
``server.port.FleetPort``. The call direction, top to bottom (no module imports one above it):

- ``fleet``: builds the robots and composes the parts below; starts and stops the threads;
- ``loop`` (the control tick) and ``operators`` (claims, commands, pauses, resets, views);
- ``lifecycle``: a robot's worker, episodes and takeovers, the transitions both of them make;
- ``policy_swap`` and ``slots`` (which policy version drives a robot), ``recording`` (what is written),
  ``metrics`` (the figures and the operators' clock), ``assistance`` (the queue and its leases);
- ``robot`` (a robot's record and published view), ``modes`` (``FleetMode``), ``handovers`` and
  ``commands`` (the mailboxes an API call leaves for the next tick).
"""

from server.fleet.fleet import Fleet
from server.fleet.metrics import MetricsReport
from server.fleet.modes import FleetMode
from server.fleet.robot import RobotView

__all__ = ["Fleet", "FleetMode", "MetricsReport", "RobotView"]

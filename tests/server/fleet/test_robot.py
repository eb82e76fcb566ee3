"""A robot's timeline: one point per clock step; holding while waiting keeps the point it asked at."""

from server.fleet.inbox import Inbox
from server.fleet.robot import Robot, TimelinePoint
from sim.spaces import TeleopLimits
from tests.helpers import tiny_policy  # noqa: F401 - the package's helpers import torch once


def test_holding_updates_the_last_point_and_keeps_its_scores():
    robot = Robot(id=0, task="lift-cube", slot=None, seed=0, inbox=Inbox(TeleopLimits()))
    robot.record(TimelinePoint(0, "autonomous", 0.1, 1.0))
    robot.record(TimelinePoint(1, "waiting", 0.9, 2.0))  # asked at clock 1
    robot.record(TimelinePoint(1, "waiting", None, None))  # holds: the clock does not move
    robot.record(TimelinePoint(1, "teleop", None, None))  # claimed
    robot.record(TimelinePoint(2, "teleop", 0.5, None))
    robot.record(TimelinePoint(3, "paused", None, None))
    robot.record(TimelinePoint(3, "teleop", None, None))  # resumed: nobody took or gave control
    robot.record(TimelinePoint(4, "autonomous", 0.2, 0.5))  # handed back
    assert list(robot.timeline) == [
        TimelinePoint(0, "autonomous", 0.1, 1.0),
        TimelinePoint(1, "teleop", 0.9, 2.0, asked=True, handed=True),  # both, at the clock it asked at
        TimelinePoint(2, "teleop", 0.5, None),
        TimelinePoint(3, "teleop", None, None),
        TimelinePoint(4, "autonomous", 0.2, 0.5, handed=True),
    ]

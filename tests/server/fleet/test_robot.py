"""A robot's timeline: one point per clock step; holding while waiting keeps the point it asked at."""

from server.fleet.commands import CommandMailbox
from server.fleet.robot import Robot, TimelinePoint
from sim.spaces import TeleopLimits
from tests.helpers import tiny_policy  # noqa: F401 - the package's helpers import torch once


def test_holding_updates_the_last_point_and_keeps_its_scores():
    robot = Robot(id=0, task="lift-cube", slot=None, seed=0, commands=CommandMailbox(TeleopLimits()))
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


def _robot():
    return Robot(id=0, task="lift-cube", slot=None, seed=0, commands=CommandMailbox(TeleopLimits()))


def test_the_fleet_names_the_controllers_modes_alike():
    from policy.controller import Mode
    from server.fleet.modes import FleetMode

    assert {m.value for m in Mode} <= {m.value for m in FleetMode}
    assert all(FleetMode.of(m) == m.value for m in Mode)


def test_a_paused_robot_stays_paused_and_resumes_into_the_mode_the_loop_left_it_in():
    from server.fleet.modes import FleetMode

    robot = _robot()
    robot.set_mode(FleetMode.WAITING)
    robot.pause()
    assert robot.mode == FleetMode.PAUSED and robot.paused_from == FleetMode.WAITING
    robot.pause()  # a second pause changes nothing
    assert robot.paused_from == FleetMode.WAITING
    robot.set_mode(FleetMode.DONE)  # the episode ended meanwhile, and the next one began
    robot.set_mode(FleetMode.AUTONOMOUS)
    assert robot.mode == FleetMode.PAUSED and robot.paused_from == FleetMode.AUTONOMOUS
    robot.resume(robot.paused_from)
    assert robot.mode == FleetMode.AUTONOMOUS and robot.paused_from is None
    robot.pause()
    robot.set_mode(FleetMode.FAULTED)  # a fault ends a pause
    assert robot.mode == FleetMode.FAULTED and robot.paused_from is None
    robot.publish()
    assert robot.view.mode == FleetMode.FAULTED

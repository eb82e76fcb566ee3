"""A robot's control state: one record of its mode and counters, changed only through its transitions, and
only by the thread bound to write it."""

import threading

import numpy as np
import pytest

from policy.hitl_state import Mode, RobotControl, WrongWriter

HOLD = np.r_[[0.1, 0.2, 0.3], [0, 1, 0, 1, 0, 0], -1.0]


def test_a_paused_robot_stays_paused_and_resumes_into_the_mode_the_loop_left_it_in():
    c = RobotControl()
    c.ask(HOLD)
    c.pause()
    assert c.mode == Mode.PAUSED and c.paused_from == Mode.WAITING
    c.pause()  # a second pause changes nothing
    assert c.paused_from == Mode.WAITING and c.stepped_mode == Mode.WAITING
    c.episode_ended()  # the episode ended meanwhile, and the next one began
    c.new_episode()
    assert c.mode == Mode.PAUSED and c.paused_from == Mode.AUTONOMOUS
    assert c.resume() == Mode.AUTONOMOUS and c.mode == Mode.AUTONOMOUS and c.paused_from is None
    c.ask(HOLD)
    c.take_over(4)
    c.pause()
    assert c.resume() == Mode.TELEOP and c.teleop_left == 4  # resumed into the takeover, its budget kept
    c.pause()
    c.fault()  # a fault ends a pause
    assert c.mode == Mode.FAULTED and c.paused_from is None
    c.restart()
    assert c.mode == Mode.AUTONOMOUS


def test_a_budgeted_request_hands_back_after_its_budget_and_the_cooldown_counts_policy_steps():
    c = RobotControl()
    c.ask(HOLD)
    assert c.mode == Mode.WAITING and np.array_equal(c.hold, HOLD)
    c.take_over(3)
    assert c.mode == Mode.TELEOP and c.teleop_left == 3
    assert not c.operator_step(True, True, None, None)
    assert not c.operator_step(True, True, None, None)
    assert c.teleop_left == 1
    assert c.operator_step(True, True, None, None)  # the third step uses the budget up
    c.hand_back(2)
    assert c.mode == Mode.AUTONOMOUS and c.cooldown == 2 and c.teleop_left is None and c.hold is None
    c.count_down()
    c.count_down()
    c.count_down()
    assert c.cooldown == 0


def test_the_calm_run_hands_back_after_return_after_steps_on_which_the_signal_no_longer_wants_help():
    c = RobotControl()
    c.ask(HOLD)
    c.take_over(None)  # continuous: no budget
    assert not c.operator_step(True, False, None, 2)
    assert not c.operator_step(True, True, None, 2)  # it wants help again: the run starts over
    assert c.calm == 0
    assert not c.operator_step(True, False, None, 2)
    assert c.operator_step(True, False, None, 2)
    assert not RobotControl().operator_step(True, False, None, None)  # without return_after never


def test_a_request_stays_engaged_until_a_step_the_policy_agreed_on_settles_it():
    c = RobotControl()
    c.policy_step(True)  # the asking signal wants help
    assert c.engaged and c.agreed is None and not c.driven
    c.ask(HOLD)
    c.take_over(4)
    c.operator_step(True, True, False, None)  # the policy disagrees with the operator's step
    assert c.agreed is False and c.driven
    c.hand_back(0)
    c.policy_step(True)  # asked again to carry on
    assert c.engaged and c.agreed is None and not c.driven
    c.ask(HOLD)
    c.take_over(4)
    c.operator_step(True, False, True, None)  # now it agrees
    c.hand_back(0)
    c.policy_step(False)  # settled
    assert not c.engaged
    c.policy_step(False)
    assert not c.engaged
    c.new_episode()
    assert (c.engaged, c.agreed, c.driven, c.cooldown, c.watched) == (False, None, False, 0, False)


def test_only_the_bound_thread_changes_the_state():
    c = RobotControl()
    errors = []
    ready, done = threading.Event(), threading.Event()

    def loop():
        c.bind_writer(threading.current_thread())
        ready.set()
        done.wait(5)
        try:
            c.ask(HOLD)  # the bound thread may
        except WrongWriter as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=loop)
    t.start()
    ready.wait(5)
    with pytest.raises(WrongWriter, match="written by its control loop only"):
        c.ask(HOLD)
    with pytest.raises(WrongWriter):
        c.pause()
    assert c.mode == Mode.AUTONOMOUS  # the refused change left nothing behind
    done.set()
    t.join(5)
    assert not errors and c.mode == Mode.WAITING
    c.bind_writer(None)
    c.pause()  # unbound: any thread
    assert c.mode == Mode.PAUSED


def test_the_state_has_no_public_setter():
    c = RobotControl()
    for name in ("mode", "teleop_left", "cooldown", "calm", "engaged", "agreed", "driven", "watched", "hold"):
        with pytest.raises(AttributeError):
            setattr(c, name, None)

"""The gripper command in force, as the hold action and the probe centre read it."""

import numpy as np

from policy.calibrate import current_actions
from sim.frame import RobotFrame
from sim.registry import make_expert


class _Recorded:
    """The two arrays ``current_actions`` reads from a dataset, for one recorded episode."""

    def __init__(self, poses, actions):
        self.ee_pose, self.actions = np.asarray(poses), np.asarray(actions)


def test_after_a_grasp_the_hold_action_keeps_the_gripper_closed_as_calibration_does(task_cache):
    task = task_cache("lift-cube")
    task.reset(3)
    assert task.hold_action()[9] == -1.0  # open before the first step
    expert = make_expert("lift-cube")
    expert.reset(task, np.random.default_rng(0))
    poses, actions, holds = [], [], []
    for _ in range(120):
        frame = RobotFrame.from_task(task)
        poses.append(np.r_[frame.pos, frame.quat])
        holds.append(frame.hold)
        action = task.teleop(expert.act(task)).action
        actions.append(action)
        task.step(action)
        if expert.phase == "lift":
            break
    else:
        raise AssertionError("the expert never closed the gripper on the cube")
    assert actions[-1][9] == 1.0 and task.hold_action()[9] == 1.0  # holding while grasping keeps it closed
    assert RobotFrame.from_task(task).gripper_command == 1.0
    # the probe centre's gripper at every step is the one calibration uses for a recorded step
    rows = np.arange(len(actions))
    centres = current_actions(_Recorded(poses, actions), rows, np.zeros_like(rows))
    np.testing.assert_array_equal(np.stack(holds)[:, 9], centres[:, 9])
    np.testing.assert_allclose(np.stack(holds)[:, :3], centres[:, :3])

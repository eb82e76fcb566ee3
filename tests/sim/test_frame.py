"""The gripper command in force, as the hold action and the probe centre read it."""

import numpy as np
import pytest

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


def test_a_viewer_poses_the_drawers_cabinet_where_the_episode_placed_it(task_cache):
    """The cabinet is placed by its position in the model, not by a joint: a viewer's copy of the model
    posed from ``qpos`` alone draws it (and its drawers) where the model was built; with the frame's
    ``placed`` bodies, where the episode put it."""
    import copy

    import mujoco

    from sim.frame import pose_model

    task = task_cache("open-drawer")
    task.reset(7)
    frame = RobotFrame.from_task(task)
    assert set(frame.placed) == {task.cabinet.root_body}
    handles = task.handle_positions()
    sites = [mujoco.mj_name2id(task.mj_model(), mujoco.mjtObj.mjOBJ_SITE, f"cabinet_handle_site{i}") for i in range(3)]

    def viewer(placed):
        model = copy.deepcopy(task.mj_model())
        model.body_pos[task.body_id(task.cabinet.root_body)] = 0.0  # as a model built for another episode may have it
        data = mujoco.MjData(model)
        pose_model(model, data, frame.qpos, placed)
        return data.site_xpos[sites]

    np.testing.assert_allclose(viewer(frame.placed), handles, atol=1e-9)
    assert np.abs(viewer({}) - handles).max() > 0.5  # qpos alone leaves it at the model's origin
    with pytest.raises(ValueError, match="no body"):
        viewer({"no_such_body": frame.placed[task.cabinet.root_body]})

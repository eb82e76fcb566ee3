"""The policy's cameras (``sim.vision``), rendered for real through OSMesa: each task declares the paper's
cameras, frames carry what they see after every step, and the cheap drawing keeps what a policy must tell
apart (the red and the green cup, the robot in its own colours)."""

import dataclasses

import numpy as np
import pytest

from sim.env import ROBOT_OBS
from sim.frame import RobotFrame
from sim.registry import make_expert, make_task
from sim.vision import COLLISION_GROUP, POLICY_CAMERAS, ROBOT_PREFIXES, VISUAL_GROUP, CameraSpec, fast_model


def test_a_camera_spec_names_a_known_camera_and_a_crop_within_its_size():
    assert CameraSpec.from_json(CameraSpec("wrist", 84, 76).to_json()) == CameraSpec("wrist", 84, 76)
    with pytest.raises(ValueError, match="unknown camera 'top'"):
        CameraSpec("top")
    with pytest.raises(ValueError, match="crop <= size"):
        CameraSpec("front", 64, 76)


def test_each_task_declares_the_papers_cameras():
    names = {name: [c.name for c in make_task(name).cameras] for name in ("lift-cube", "cup-stack", "open-drawer")}
    assert names["lift-cube"] == ["front", "wrist"]
    assert names["cup-stack"] == ["side", "wrist", "front"]  # the paper: without the wrist view no grasp
    assert names["open-drawer"] == ["side"]  # one view that sees the arm and the drawers' handles
    assert {c.crop for c in make_task("lift-hook").cameras} == {76}  # the paper's Lift-sim crop


def _small(task, size=32, crop=24):
    """The task with its cameras at a test's size (the cost is geometry, so the scene is the same)."""
    task.cameras = tuple(dataclasses.replace(c, size=size, crop=crop) for c in type(task).cameras)
    return task


def test_frames_carry_what_the_cameras_see_after_every_step_only_when_asked():
    task = _small(make_task("lift-cube", images=True))
    plain = make_task("lift-cube")
    try:
        task.reset(3)
        first = RobotFrame.from_task(task)
        assert set(first.images) == {"front", "wrist"}
        assert all(im.shape == (32, 32, 3) and im.dtype == np.uint8 for im in first.images.values())
        expert = make_expert("lift-cube")
        expert.reset(task, np.random.default_rng(0))
        for _ in range(15):  # the arm moves towards the cube: the wrist camera moves with it
            frame = RobotFrame.from_task(task, task.step(task.teleop(expert.act(task)).action))
        assert np.abs(frame.images["wrist"].astype(int) - first.images["wrist"]).mean() > 1.0
        plain.reset(3)
        assert RobotFrame.from_task(plain).images == {}  # a low-dimensional policy's frames render nothing
        # a policy that sees observes the robot's own state besides the images: no object pose, box or ray
        assert task.obs_spec.labels() == ROBOT_OBS.labels() and frame.obs.shape == (ROBOT_OBS.dim,)
        np.testing.assert_allclose(frame.obs, task.robot_obs(), atol=1e-6)
        assert "object_pos" in [n for n, _ in type(task).obs_spec.parts]  # experts and tests keep the state
    finally:
        task.close()
        plain.close()


def test_the_cheap_drawing_draws_the_robot_from_its_collision_geoms_in_its_own_colours():
    task = make_task("cup-stack")
    try:
        task.reset(0)
        model = task.mj_model()
        fast = fast_model(model)
        import mujoco

        body = mujoco.mjtObj.mjOBJ_BODY
        robot = [
            g
            for g in range(model.ngeom)
            if (mujoco.mj_id2name(model, body, model.geom_bodyid[g]) or "").startswith(ROBOT_PREFIXES)
        ]
        drawn = [g for g in robot if fast.geom_group[g] == VISUAL_GROUP]
        assert drawn and all(model.geom_group[g] == COLLISION_GROUP for g in drawn)  # collision geoms, now drawn
        assert all(fast.geom_matid[g] == -1 for g in drawn)
        assert not np.allclose(fast.geom_rgba[drawn], model.geom_rgba[drawn])  # not MuJoCo's default colours
        assert fast.vis.quality.offsamples == 0 and model.vis.quality.offsamples > 0  # the task's own model unchanged
        assert any(model.geom_group[g] == VISUAL_GROUP for g in robot)  # the live model still draws its meshes
        assert not any(fast.geom_group[g] == COLLISION_GROUP for g in range(fast.ngeom))  # nothing else's collision
    finally:
        task.close()


def test_the_cups_keep_their_colours_in_every_cup_stack_camera():
    """The policy tells the cups apart by colour: red pixels and green pixels in the side and front views."""
    task = _small(make_task("cup-stack"), size=64, crop=56)
    try:
        task.reset(0)
        for name, image in task.images().items():
            rgb = image.astype(int)
            red = ((rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60)).sum()
            green = ((rgb[..., 1] > rgb[..., 0] + 40) & (rgb[..., 1] > rgb[..., 2] + 20)).sum()
            if name != "wrist":  # the wrist camera looks down at one cup at a time
                assert red > 3 and green > 3, (name, red, green)
        assert set(POLICY_CAMERAS) >= {c.name for c in task.cameras}
    finally:
        task.close()

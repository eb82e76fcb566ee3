"""Camera views (``server.cameras``): the real renderer process (MuJoCo through OSMesa) renders watched
robots' front and wrist cameras from their frames' joint positions; when no renderer starts, or it dies
mid-run, the feed says so and stays off; a takeover segment carries the views its operator saw, as
``foxglove.CompressedImage`` that an MCAP reader gives back as JPEG."""

import dataclasses
import io
import time

import numpy as np
import pytest
from PIL import Image

from server.cameras import CameraFeed
from sim.frame import RobotFrame
from sim.registry import make_task
from storage.segments import SegmentWriter, read_segment
from tests.helpers import wait_for


@pytest.fixture(scope="module")
def frames():
    """Two lift-cube frames from real episodes whose cubes lie in different places."""
    out = []
    for seed in (1, 2):
        task = make_task("lift-cube")
        try:
            task.reset(seed)
            out.append(RobotFrame.from_task(task))
        finally:
            task.close()
    return out


def _off(feed):
    view = feed.view(0)
    return view if not view.available else None


def _newer(feed, than):
    images = feed.view(0).images
    return images if images is not None and images.rendered_at > than.rendered_at else None


def _rgb(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"))


def test_a_watched_robot_is_rendered_from_its_frame_and_each_new_frame_once(frames):
    current = {0: frames[0]}
    seen = []
    feed = CameraFeed(lambda rid: ("lift-cube", current[rid]), seen.append, hz=20.0, size=(96, 72))
    try:
        assert feed.process is None  # nothing runs until someone watches
        first = wait_for(lambda: feed.view(0).images, timeout=180)
        assert set(first.images) == {"front", "wrist"} and first.t == frames[0].t
        front = _rgb(first.images["front"])
        assert front.shape == (72, 96, 3) and front.std() > 5  # a picture, not a blank
        time.sleep(0.5)
        assert len(seen) == 1  # the same frame is not rendered again
        current[0] = frames[1]
        second = wait_for(
            lambda: (v := feed.view(0).images) is not None and v.rendered_at > first.rendered_at and v, 60
        )
        assert np.abs(_rgb(second.images["front"]).astype(int) - front.astype(int)).mean() > 0.5  # the cube moved
        assert [s.robot_id for s in seen] == [0, 0]
    finally:
        feed.close()


def test_a_policy_that_sees_shows_the_operator_its_own_frames_rendered_once(frames):
    policy_frames = {"front": np.zeros((84, 84, 3), np.uint8), "wrist": np.full((84, 84, 3), 200, np.uint8)}
    policy_frames["front"][:42] = 255  # its top half white: what the policy saw, not a render of the scene
    seeing = dataclasses.replace(frames[0], images=policy_frames)
    feed = CameraFeed(lambda rid: ("lift-cube", seeing), hz=20.0, size=(96, 72))
    try:
        views = wait_for(lambda: feed.view(0).images, timeout=180)
        front, wrist = _rgb(views.images["front"]), _rgb(views.images["wrist"])
        assert front.shape == (72, 72, 3) and (views.width, views.height) == (72, 72)
        assert front[:30].mean() > 240 and front[42:].mean() < 15  # the policy's frame, scaled up
        assert abs(wrist.mean() - 200) < 5
    finally:
        feed.close()


def test_the_views_show_the_drawers_cabinet_where_the_frame_placed_it():
    """The cabinet has no joint (``RobotFrame.placed``): the renderer moves it as the frame says."""
    task = make_task("open-drawer")
    try:
        task.reset(3)
        frame = RobotFrame.from_task(task)
    finally:
        task.close()
    ((root, (pos, quat)),) = frame.placed.items()
    moved = dataclasses.replace(frame, t=frame.t + 1, placed={root: (pos + np.array([0.0, 0.15, 0.0]), quat)})
    current = {0: frame}
    feed = CameraFeed(lambda rid: ("open-drawer", current[rid]), hz=20.0, size=(96, 72))
    try:
        first = wait_for(lambda: feed.view(0).images, timeout=180)
        current[0] = moved
        second = wait_for(lambda: _newer(feed, first), 60)
        assert second.t == moved.t
        change = np.abs(_rgb(second.images["front"]).astype(int) - _rgb(first.images["front"]).astype(int)).mean()
        assert change > 2.0  # the cabinet moved 15 cm across the front camera's view
    finally:
        feed.close()


def test_without_a_renderer_the_feed_says_why_and_stays_off(frames):
    # OSMesa refuses to load under another PyOpenGL platform: no OpenGL context comes up
    feed = CameraFeed(lambda rid: ("lift-cube", frames[0]), env={"PYOPENGL_PLATFORM": "egl"})
    try:
        assert feed.view(0).available
        view = wait_for(lambda: _off(feed), timeout=120)
        assert "no camera renderer" in view.reason and view.images is None
    finally:
        feed.close()
    off = CameraFeed(lambda rid: ("lift-cube", frames[0]), enabled=False)
    assert not off.view(0).available and "cameras.enabled = false" in off.view(0).reason and off.process is None


def test_a_renderer_that_dies_mid_run_turns_the_views_off_with_the_reason(frames):
    current = {0: frames[0]}
    feed = CameraFeed(lambda rid: ("lift-cube", current[rid]), hz=20.0, size=(64, 48))
    try:
        wait_for(lambda: feed.view(0).images, timeout=180)
        feed.process.kill()
        current[0] = frames[1]  # a new frame to render: the dead process is found
        view = wait_for(lambda: _off(feed), timeout=60)
        assert "failed mid-run" in view.reason and view.images is None
    finally:
        feed.close()


def test_a_segment_carries_the_views_as_compressed_images_an_mcap_reader_gives_back(tmp_path):
    from mcap.reader import make_reader

    jpeg = io.BytesIO()
    Image.fromarray(np.full((12, 16, 3), (200, 30, 30), np.uint8)).save(jpeg, format="JPEG")
    writer = SegmentWriter(tmp_path / "seg.mcap", {"robot": 0})
    writer.write_image("front", jpeg.getvalue(), 7)
    writer.write_image("wrist", jpeg.getvalue(), 7)
    writer.write_image("front", jpeg.getvalue(), 8)
    writer.close()
    seg = read_segment(tmp_path / "seg.mcap")
    assert sorted(seg.images) == ["front", "wrist"] and len(seg.images["front"]) == 2
    msg = seg.images["front"][1]
    assert msg["format"] == "jpeg" and msg["frame_id"] == "step-8" and set(msg["timestamp"]) == {"sec", "nsec"}
    assert _rgb(seg.jpeg(msg))[0, 0, 0] > 150  # the red picture back
    with open(tmp_path / "seg.mcap", "rb") as f:  # what any MCAP reader sees: the schema and the topics
        channels = {c.topic: s.name for s, c, _ in make_reader(f).iter_messages()}
    assert channels["/camera/front/image/compressed"] == "foxglove.CompressedImage"
    assert channels["/camera/wrist/image/compressed"] == "foxglove.CompressedImage"

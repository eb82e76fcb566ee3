"""The console's pure parts: the signed identity, viser message types, the field's arrows in world
units, the U timeline's events, and the panel text."""

import time

import msgspec
import numpy as np

from policy.normalizer import MinMaxNormalizer
from policy.uncertainty import UncertaintyResult
from server.fleet.inbox import Inbox
from server.fleet.robot import Robot, TimelinePoint
from sim.registry import make_task
from sim.spaces import TeleopLimits
from web.identity import Identity, IdentitySigner
from web.panels import key_map_markdown, timeline_data
from web.scene import FIELD_LONGEST_M, MODE_COLORS, field_arrows, pose_delta, probe_radii
from web.viser_internals import message_type


def test_a_signed_identity_verifies_and_a_tampered_or_expired_one_does_not():
    signer = IdentitySigner()
    value = signer.sign(Identity("alice", "operator"))
    assert signer.verify(value) == Identity("alice", "operator")
    payload, mac = value.split(".")
    forged = IdentitySigner().sign(Identity("alice", "admin")).split(".")[0] + "." + mac
    assert signer.verify(forged) is None  # another payload under alice's signature
    assert IdentitySigner().verify(value) is None  # another key
    assert signer.verify(None) is None and signer.verify("") is None and signer.verify("a.b.c") is None
    # header bytes that are not ASCII arrive as surrogates: refused, never an exception in viser's handler
    assert signer.verify(payload + ".\udcff\udcfe") is None and signer.verify("é\udcff." + mac) is None
    short = IdentitySigner(ttl_s=0.01)
    old = short.sign(Identity("bob", "viewer"))
    time.sleep(0.05)
    assert short.verify(old) is None


def test_message_types_are_read_from_msgpack_and_garbage_has_none():
    assert message_type(msgspec.msgpack.encode({"type": "ShareUrlRequest"})) == "ShareUrlRequest"
    assert message_type(msgspec.msgpack.encode([1, 2])) is None
    assert message_type(b"\xff\x00garbage") is None


def _normalizer(low, high):
    n = MinMaxNormalizer(10)
    n.set_bounds(np.asarray(low, np.float64), np.asarray(high, np.float64))
    return n


def test_field_arrows_are_in_world_units_around_the_probe_centre():
    low = [0.0, -1.0, 0.5] + [-1.0] * 7
    high = [1.0, 1.0, 1.5] + [1.0] * 7
    norm = _normalizer(low, high)
    samples = np.array([[0.5, 0.5, 0.5], [0.55, 0.5, 0.5], [0.5, 0.45, 0.5]])  # normalized
    vectors = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, -0.1]])  # ε: arrows point along -ε
    result = UncertaintyResult(
        samples=samples,
        vectors=vectors,
        labels=np.array([0, 1, 1]),
        means=np.array([[0.1, 0, 0], [0, 0.1, 0]]),
        weights=np.array([0.4, 0.6]),
        n=2,
        D=1.0,
        var_g=0.1,
        U=1.1,
    )
    centre = np.array([0.5, 0.0, 1.0])  # the world point of the normalized samples[0]
    arrows = field_arrows(result, norm, centre)
    np.testing.assert_allclose(arrows.field[:, 0], [[0, 0, 0], [0.05, 0, 0], [0, -0.1, 0]], atol=1e-6)
    direction = arrows.field[:, 1] - arrows.field[:, 0]
    lengths = np.linalg.norm(direction, axis=1)
    assert np.isclose(lengths.max(), FIELD_LONGEST_M, atol=1e-6)  # the longest, at the set length
    # -ε scaled per axis by the bounds' span (1, 2, 1 m): (-0.1, 0, 0), (0, -0.4, 0), (0, 0, 0.1)
    np.testing.assert_allclose(direction / lengths.max() * 0.4, [[-0.1, 0, 0], [0, -0.4, 0], [0, 0, 0.1]], atol=1e-6)
    np.testing.assert_array_equal(arrows.colors, MODE_COLORS[[0, 1, 1]])
    assert arrows.modes.shape == (2, 2, 3)  # one bold arrow per mode, from its samples' centroid
    np.testing.assert_allclose(arrows.modes[1, 0], arrows.field[1:, 0].mean(axis=0), atol=1e-6)
    assert np.dot(arrows.modes[0, 1] - arrows.modes[0, 0], [-1, 0, 0]) > 0  # a mode mean points along -ε too
    np.testing.assert_allclose(probe_radii(norm, 0.05), [0.05, 0.1, 0.05])


def test_pose_delta_is_the_world_frame_step_to_a_target():
    from scipy.spatial.transform import Rotation

    class Frame:
        pos = np.array([0.1, 0.2, 0.3])
        quat = Rotation.from_euler("z", 10, degrees=True).as_quat()

    target = Rotation.from_euler("z", 25, degrees=True).as_quat()  # xyzw
    delta_pos, delta_rot = pose_delta(np.array([0.12, 0.2, 0.29]), np.roll(target, 1), Frame)
    np.testing.assert_allclose(delta_pos, [0.02, 0.0, -0.01], atol=1e-12)
    np.testing.assert_allclose(delta_rot, [0, 0, np.radians(15)], atol=1e-9)


class _Slot:
    threshold = 2.0
    asking = "spread"
    version = 1

    class controller:  # noqa: N801 - the attribute the panel reads
        class _Signal:
            threshold = 0.5

        signals = {"spread": _Signal()}


class _View:
    slot = _Slot()

    def __init__(self, modes):
        robot = Robot(id=0, task="lift-cube", slot=None, seed=0, inbox=Inbox(TeleopLimits()))
        for t, m in enumerate(modes):
            robot.record(TimelinePoint(t, m, 0.25 * (t + 1), 1.0 if t % 2 else None))
        self.timeline = tuple(robot.timeline)


def test_the_timeline_marks_requests_and_changes_of_hands():
    modes = ["autonomous", "autonomous", "waiting", "waiting", "teleop", "teleop", "autonomous"]
    t, score, u, threshold, asked, handed = timeline_data(_View(modes))
    np.testing.assert_array_equal(t, np.arange(7))
    np.testing.assert_allclose(score, 0.25 * (t + 1) / 0.5)  # relative to the asking signal's threshold
    assert np.isnan(u[0]) and u[1] == 0.5  # U / 2.0; None is a gap
    np.testing.assert_array_equal(threshold, np.ones(7))
    assert list(np.flatnonzero(~np.isnan(asked))) == [2]
    assert list(np.flatnonzero(~np.isnan(handed))) == [4, 6]


def test_a_robot_without_points_has_a_timeline_with_a_span_not_empty_arrays():
    """viser's uPlot takes its x range from the first data it gets: empty arrays leave it drawing nothing."""
    t, *series = timeline_data(_View([]))
    assert len(t) == 2 and t[1] > t[0]
    assert all(len(s) == 2 for s in series) and np.isnan(series[0]).all()


def test_the_goal_and_the_key_map_read_as_an_operator_needs_them():
    # each task says its own goal from the frame's scene (its privileged state as JSON), no simulation needed
    drawer, cups, hook = make_task("open-drawer"), make_task("cup-stack"), make_task("lift-hook")
    assert drawer.goal({"intended": 2}).text == "Open the **left** drawer (the robot does not know which)."
    assert drawer.goal({}).text == drawer.description
    hidden = " The red cup is hidden from the robot's camera."
    assert cups.goal({"red_visible": False}).text == f"{cups.description}.{hidden}"
    assert cups.goal({"red_visible": True}).text == f"{cups.description}."
    bar = "Lift the hook 4 cm off the table; grasp across its bar (yaw -90°)."
    assert hook.goal({"grasp_yaw": -np.pi / 2}).text == bar
    keys = key_map_markdown()
    assert "W/A/S/D/Q/E" in keys  # left to the camera, and said so
    for key in ("| I / K |", "| J / L |", "| U / O |", "| N / M |", "| G |"):
        assert key in keys


def test_the_fleet_tab_shows_each_lineage_and_its_last_job():
    from server.registry import LineageSummary
    from web.panels import lineage_markdown

    assert lineage_markdown(()) == ""
    idle = LineageSummary("lift-cube", "lift-cube@1", "configured", None, 1, 0)
    running = LineageSummary(
        "cup-stack", "cup-stack@2", "gate passed: ...", "cup-stack@1", 3, 1, 7, "running", "train", 0.4
    )
    done = LineageSummary(
        "open-drawer",
        "open-drawer@1",
        "promoted",
        None,
        2,
        1,
        9,
        "succeeded",
        "done",
        1.0,
        "not better on open-drawer: 0.40 against 0.45",
        False,
        None,
        "2026-11-24T03:12+00:00",
    )
    failed = LineageSummary("x", None, None, None, 1, 1, 3, "failed", "data", 0.02, None, None, "no usable sample")
    text = lineage_markdown((idle, running, done, failed))
    rows = text.splitlines()[2:]
    assert rows[0] == "| lift-cube | lift-cube@1 | – · configured | none yet |"
    assert "cup-stack@2 · 1 candidate(s)" in rows[1] and "#7 running · train 40%" in rows[1]
    assert "#9 kept as candidate (2026-11-24T03:12+00:00): not better on open-drawer" in rows[2]
    assert rows[3].endswith("| #3 failed: no usable sample |")


def test_the_takeover_list_shows_notes_and_names_as_text_never_as_html():
    """viser renders a markdown's raw HTML unsanitized: an operator's note must not become markup in the
    other operators' consoles."""
    import markdown_it

    from web.takeovers import TakeoverRow, takeovers_markdown

    note = "<img src=x onerror=alert(1)> **loud** | [link](javascript:alert(2)) a-b\nsecond line"
    row = TakeoverRow(3, "eve<script>", 4, "closed", "hand-back", "bad", True, note, "eve")
    text = takeovers_markdown([row])
    assert "<img" not in text and "<script" not in text
    rendered = markdown_it.MarkdownIt().enable("table").render(text)
    assert "<img" not in rendered and "<script" not in rendered and "<a " not in rendered
    assert "<strong>loud" not in rendered and rendered.count("<td>") == 6  # the pipe did not split the cell
    cells = rendered.split("<td>")
    assert "&lt;img src=x onerror=alert(1)&gt; **loud** | [link](javascript:alert(2)) a-b second line" in cells[6]
    assert "bad, <strong>discarded</strong>" in rendered  # our own markup still renders
    # a lease holder's name (a token's) is text too
    from server.fleet.assistance import AssistanceRequest
    from web.panels import queue_row

    req = AssistanceRequest(1, 0, 1.0, 0.5, "spread: over", created=0.0, holder="<img src=x onerror=alert(3)>")
    assert "<img" not in queue_row(req, None, 1.0, "someone else") and "&lt;img" in queue_row(req, None, 1.0, "me")


def test_the_panel_shows_the_request_a_robot_waits_on_and_the_papers_u_apart():
    """A waiting robot shows its request's signal, score and threshold (the queue's); one without a request,
    its asking signal's latest score; the paper's U stays in a column of its own."""
    from server.fleet.assistance import AskRecord, AssistanceQueue
    from web.panels import FleetSnapshot, overview_markdown, robot_markdown

    robot = Robot(id=0, task="lift-cube", slot=_Slot(), seed=0, inbox=Inbox(TeleopLimits()))
    robot.scores = {"spread": 0.3}
    robot.u_history.append(0.062)
    robot.publish()
    glance, scores = overview_markdown(FleetSnapshot({0: robot.view}, ()), "me").split("\n\n")
    assert glance.splitlines()[0] == "| Robot | Task | Mode | Episode step | Why it waits |"
    assert glance.splitlines()[2] == "| 0 | lift-cube | autonomous | – |  |"  # no frame yet, works alone
    assert scores.splitlines()[0].startswith("| Robot | Asking: score / threshold | Paper's U / threshold |")
    assert scores.splitlines()[2].startswith("| 0 | spread: 0.3 / 0.5 | 0.062 / 2 |")
    queue = AssistanceQueue(10.0)
    robot.ask = queue.ask(0, AskRecord("spread", 2.4, 0.5, "spread: stall 2.4× its threshold", 7, 0.062)).ask
    robot.control.ask(np.zeros(10))
    robot.publish()
    snap = FleetSnapshot({0: robot.view}, tuple(queue.pending()))
    glance, scores = overview_markdown(snap, "me").split("\n\n")
    assert glance.splitlines()[2].endswith("| spread: stall 2.4× its threshold |")  # why, in the queue's words
    assert scores.splitlines()[2].startswith("| 0 | spread: 2.4 / 0.5 ⚠ | 0.062 / 2 |")
    text = robot_markdown(robot.view, snap.request(0), snap.now, "me", make_task("lift-cube"))
    assert "| **spread** (asked at step 7) | 2.4 | 0.5 |" in text
    assert "**Asked:** spread: stall 2.4× its threshold" in text


def test_the_fleet_table_keeps_a_reason_inside_its_cell_and_says_where_each_episode_is():
    """A reason with a pipe, a newline or markup stays one cell of text; a faulted robot says why; the episode
    column reads the frame's step of its horizon."""
    from types import SimpleNamespace

    from server.fleet.assistance import AssistanceRequest
    from web.panels import _cell, why_waits

    assert _cell("a | b\nc <b>") == "a \\| b c &lt;b&gt;"
    assert _cell("x" * 200).endswith("…") and len(_cell("x" * 200)) == 60
    view = SimpleNamespace(mode="faulted", fault="worker exited with code -9")
    assert why_waits(view, None) == "fault: worker exited with code -9"
    req = AssistanceRequest(1, 0, 1.0, 0.5, "watchdog: 120 of 150 steps without success")
    assert why_waits(SimpleNamespace(mode="waiting", fault=None), req) == req.reason
    assert why_waits(SimpleNamespace(mode="paused", fault=None), None) == "paused by an admin"
    assert why_waits(SimpleNamespace(mode="autonomous", fault=None), None) == ""


def test_the_scene_draws_no_stray_objects_only_the_tasks_visual_geoms():
    """robosuite's end-effector target markers (mocap bodies parked at z = -1 m, under the table) and its
    collision geoms are hidden; the objects' visual geoms stay."""
    import mujoco

    from web.viser_internals import HIDDEN_GROUP, hide_model_groups

    task = make_task("lift-cube")
    try:
        model = task.mj_model()
        hide_model_groups(model)
        shown = [
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g])
            for g in range(model.ngeom)
            if model.geom_group[g] != HIDDEN_GROUP
        ]
    finally:
        task.close()
    assert not [b for b in shown if "eef_target" in b]
    assert "cube_main" in shown and "table" in shown


def test_the_scene_draws_the_drawers_cabinet_where_each_episode_placed_it():
    """mjviser draws a body welded to the world once, where the model had it; the scene moves the
    cabinet (placed per episode without a joint) to each frame's place, and its drawers with it."""
    import copy
    from types import SimpleNamespace

    import mujoco
    import torch
    import viser

    from sim.frame import RobotFrame
    from tests.helpers import free_port
    from web.scene import RobotScene
    from web.viser_internals import quiet

    task = make_task("open-drawer")
    try:
        frames = []
        for seed in (3, 4):
            task.reset(seed)
            frames.append(RobotFrame.from_task(task))
        model = copy.deepcopy(task.mj_model())
        root = task.cabinet.root_body
    finally:
        task.close()
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root)
    model.body_pos[body] = 0.0  # where no episode puts it
    with quiet():
        server = viser.ViserServer(host="127.0.0.1", port=free_port())
    try:
        normalizer = SimpleNamespace(span=torch.ones(10))
        scene = RobotScene(server, 0, model, normalizer, 1)
        drawn = [h for (b, _, _), h in scene.mj._fixed_geom_handles.items() if b == body]
        assert drawn and np.allclose(drawn[0].position, 0.0)
        for frame in frames:
            scene.update(frame, None)
            assert all(np.allclose(h.position, frame.placed[root][0]) for h in drawn)
    finally:
        with quiet():
            server.stop()


def test_frames_from_visers_server_read_back_as_its_messages():
    """``server_messages`` reads the pinned viser's wire frames (what ``hitl bench console``'s protocol
    clients read to pick their robots)."""
    import viser
    from websockets.sync.client import connect

    from tests.helpers import free_port
    from web.viser_internals import SUBPROTOCOL, quiet, server_messages

    port = free_port()
    with quiet():
        server = viser.ViserServer(host="127.0.0.1", port=port)
    try:
        server.gui.add_dropdown("Robot", options=("0 · lift-cube", "1 · lift-cube"))
        seen: list[dict] = []
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            for _ in range(50):
                seen += server_messages(ws.recv(timeout=10))
                if any(m.get("type") == "GuiDropdownMessage" for m in seen):
                    break
        dropdown = next(m for m in seen if m.get("type") == "GuiDropdownMessage")
        assert isinstance(dropdown["uuid"], str) and dropdown["props"]["label"] == "Robot"
        assert list(dropdown["props"]["options"]) == ["0 · lift-cube", "1 · lift-cube"]
    finally:
        with quiet():
            server.stop()

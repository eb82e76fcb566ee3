"""One browser's console: the fleet overview and the queue, the robot view, the takeover inputs, and
the robot's recent takeovers with their labels (``web.takeovers``).

GUI callbacks only call ``ConsoleActions`` (the fleet's service methods with the API's checks) and set
this panel's own state; ``tick`` (the console's thread, one atomic frame) sends what changed. A user
without the lease watches read-only: the inputs are disabled, and the service would refuse them anyway.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from concurrent.futures import Executor, Future

import numpy as np
import viser

from policy.hitl_state import Mode
from server.errors import ServiceError
from server.port import FleetPort
from sim.env import Task
from sim.registry import make_task
from sim.spaces import TeleopLimits
from web.actions import ConsoleActions
from web.camera_views import CameraFolder
from web.identity import Identity
from web.panels import (
    TIMELINE_SERIES,
    FleetSnapshot,
    empty_timeline,
    key_map_markdown,
    lineage_markdown,
    overview_markdown,
    queue_head,
    queue_row,
    robot_markdown,
    timeline_data,
)
from web.scene import CAMERA_LOOK_AT, CAMERA_POSITION, RobotScene, SceneModels, pose_delta, probe_radius
from web.takeovers import TakeoverBoard, TakeoverFolder

log = logging.getLogger("hitl.console")

JOGS = (  # label, hotkey, translation axis or None, rotation axis or None, sign
    ("+X", "I", 0, None, 1.0),
    ("−X", "K", 0, None, -1.0),
    ("+Y", "J", 1, None, 1.0),
    ("−Y", "L", 1, None, -1.0),
    ("+Z", "U", 2, None, 1.0),
    ("−Z", "O", 2, None, -1.0),
    ("Yaw +", "N", None, 2, 1.0),
    ("Yaw −", "M", None, 2, -1.0),
)
HEARTBEAT_S = 1.0
GIZMO_TOLERANCE = (0.002, 0.02)  # m, rad: a dragged target counts as reached
NOTIFY_S = 8.0
FOCUS_OFFSET = np.array([0.17, 0.12, 0.05])  # m, from the end effector: the probe ball fills the middle of the view


class OperatorPanel:
    def __init__(
        self,
        client: viser.ClientHandle,
        identity: Identity,
        fleet: FleetPort,
        models: SceneModels,
        builds: Executor,
        hz: float,
        board: TakeoverBoard | None = None,
    ) -> None:
        self.client, self.identity, self.fleet, self.models, self.builds = client, identity, fleet, models, builds
        self.actions = ConsoleActions(fleet, identity, board.sessions if board is not None else None)
        self.board = board
        self.hz = hz
        self.limits = TeleopLimits()
        self.closed = False
        self._lock = threading.Lock()
        self.robot_id: int | None = None  # the robot on view
        self.scene: RobotScene | None = None
        self._building: Future | None = None
        self._sent: dict[tuple[int, str], object] = {}
        self._queue_rows: dict[int, tuple] = {}
        self._queue_key: tuple = ()
        self._known_requests: set[int] | None = None
        self._held: set[int] = set()
        self._faulted: set[int] = set()
        self._released: set[int] = set()
        self._claimed: dict[int, float] = {}  # robot -> when this browser claimed it: the only leases it renews
        self._gizmo_sent_t: tuple[int, int] | None = None  # (robot, frame t) of the last gizmo command
        self._last_heartbeat = 0.0
        self._gripper: float | None = None  # the gripper command this operator sends
        self._drag: tuple[np.ndarray, np.ndarray] | None = None
        self._dragging = False
        self._timeline_key: tuple = ()
        self._tasks: dict[str, Task] = {}  # task name -> the task, for its goal
        self._following: tuple[int, float] | None = None  # (robot, when) "follow the queue" claimed, until handed back
        self._frame_gripper: int | None = None  # a robot just claimed: frame its gripper once its scene is up
        self._build_gui()
        client.camera.position, client.camera.look_at = CAMERA_POSITION, CAMERA_LOOK_AT

    # -- building the GUI ---------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.client.gui
        gui.add_markdown(f"Logged in as **{self.identity.name}** ({self.identity.role})")
        self.follow_button = gui.add_button("Follow the queue (T)", icon=viser.Icon.PLAYER_TRACK_NEXT)
        self.follow_status = gui.add_markdown("")
        tabs = gui.add_tab_group()
        with tabs.add_tab("Robot", viser.Icon.ROBOT):
            self.robot_select = gui.add_dropdown("Robot", options=("–",), initial_value="–")
            self.focus_button = gui.add_button("Look at the gripper (F)", icon=viser.Icon.FOCUS_CENTERED)
            self.status = gui.add_markdown("Waiting for the fleet…")
            self.plot = gui.add_uplot(
                data=empty_timeline(),
                series=TIMELINE_SERIES,
                title="Timeline: asking score and the paper's U (÷ threshold)",
                aspect=2.0,
                scales={"x": {"time": False}},
            )
            with gui.add_folder("Take over"):
                self.claim_button = gui.add_button(
                    "Claim (C)", color="orange", disabled=True, icon=viser.Icon.HAND_GRAB
                )
                self.release_button = gui.add_button("Hand back (R)", disabled=True, icon=viser.Icon.ARROW_BACK_UP)
                self.step_mm = gui.add_slider("Step (mm)", min=1, max=30, step=1, initial_value=10)
                self.turn_deg = gui.add_slider("Turn (deg)", min=1, max=11, step=1, initial_value=5)
                self.jog_buttons = []
                for label, key, pos_axis, rot_axis, sign in JOGS:
                    button = gui.add_button(f"{label} ({key})", disabled=True)
                    button.on_hold(self._jog_callback(pos_axis, rot_axis, sign), callback_hz=self.hz)
                    self.jog_buttons.append(button)
                self.open_button = gui.add_button("Open gripper", disabled=True)
                self.close_button = gui.add_button("Close gripper (G toggles)", disabled=True)
            # below the takeover inputs: views that come and go must not move the buttons under the pointer
            self.cameras = CameraFolder(gui, self.fleet, self._set)
            self.takeovers = (
                TakeoverFolder(gui, self.board, self.actions, self._notify) if self.board is not None else None
            )
            with gui.add_folder("Keys", expand_by_default=False):
                gui.add_markdown(key_map_markdown())
        with tabs.add_tab("Fleet", viser.Icon.LIST):
            self.overview = gui.add_markdown("")
            self.lineages = gui.add_markdown("")
            self.queue_folder = gui.add_folder("Assistance queue")
            with self.queue_folder:
                self.queue_empty = gui.add_markdown("_No robot is waiting for help._")

        self.robot_select.on_update(lambda _: self._select(self._parse_robot(self.robot_select.value)))
        self.claim_button.on_click(lambda _: self._claim(self.robot_id))
        self.release_button.on_click(lambda _: self._release(self.robot_id))
        self.open_button.on_click(lambda _: self._set_gripper(-1.0))
        self.close_button.on_click(lambda _: self._set_gripper(1.0))
        for label, key, pos_axis, rot_axis, sign in JOGS:
            command = gui.add_command(f"Jog {label}", hotkey=key)
            command.on_trigger(self._jog_callback(pos_axis, rot_axis, sign))
        self.focus_button.on_click(lambda _: self._focus())
        self.follow_button.on_click(lambda _: self._follow())
        gui.add_command("Follow the queue", hotkey="T").on_trigger(lambda _: self._follow())
        gui.add_command("Look at the gripper", hotkey="F").on_trigger(lambda _: self._focus())
        gui.add_command("Toggle gripper", hotkey="G").on_trigger(lambda _: self._toggle_gripper())
        gui.add_command("Claim the robot on view", hotkey="C").on_trigger(lambda _: self._claim(self.robot_id))
        gui.add_command("Hand back", hotkey="R").on_trigger(lambda _: self._release(self.robot_id))

    @staticmethod
    def _parse_robot(value: str) -> int | None:
        head = value.split(" ", 1)[0]
        return int(head) if head.isdigit() else None

    # -- what the user does (callbacks: service calls and this panel's state only) -----------------
    def _notify(self, title: str, body: str, color: str | None = None) -> None:
        if not self.closed:
            self.client.add_notification(title, body, auto_close_seconds=NOTIFY_S, color=color)

    def _refused(self, what: str, exc: ServiceError) -> None:
        self._notify(f"{what} refused ({exc.status})", exc.message, "red")

    def _select(self, robot_id: int | None) -> None:
        with self._lock:
            if robot_id is not None and robot_id != self.robot_id:
                self.robot_id = robot_id
                self._drag, self._gripper = None, None

    def _focus(self) -> None:
        """Moves this browser's camera close to the end effector, where the field is readable."""
        view = self.fleet.view(self.robot_id) if self.robot_id is not None else None
        if view is not None and view.frame is not None:
            ee = np.asarray(view.frame.pos, float)
            self.client.camera.look_at = ee
            self.client.camera.position = ee + FOCUS_OFFSET

    def _follow(self) -> None:
        """Claims the robot the queue puts first and frames its gripper; says why not when the queue is empty,
        every request in it is held by someone else, or this operator still holds another robot."""
        requests = self.fleet.requests()
        mine = [r.robot_id for r in requests if r.holder == self.identity.name]
        rid, line = queue_head(requests, self.identity.name)
        if rid is None or (mine and rid not in mine):
            why = line if rid is None else f"You hold robot {mine[0]}: hand it back (R) first."
            self._notify("Follow the queue", why, "yellow")
            return
        if self._claim(rid):  # the robot this operator already holds, or the first free one
            with self._lock:
                self._following = (rid, time.monotonic())

    def _claim(self, robot_id: int | None) -> bool:
        if robot_id is None:
            return False
        try:
            self.actions.claim(robot_id)
        except ServiceError as exc:
            self._refused(f"Claiming robot {robot_id}", exc)
            return False
        self._select(robot_id)
        with self._lock:
            self._gripper = None
            self._claimed[robot_id] = time.monotonic()
            self._frame_gripper = robot_id
        return True

    def _release(self, robot_id: int | None) -> None:
        if robot_id is None:
            return
        try:
            self.actions.release(robot_id)
        except ServiceError as exc:
            self._refused(f"Handing robot {robot_id} back", exc)
            return
        with self._lock:
            self._released.add(robot_id)
            self._claimed.pop(robot_id, None)
            self._drag = None

    def _current_gripper(self, rid: int) -> float:
        if self._gripper is None:
            frame = self.fleet.view(rid).frame
            self._gripper = frame.gripper_command if frame is not None else -1.0
        return self._gripper

    def _send(self, delta_pos, delta_rot, quiet_429: bool = True, rid: int | None = None) -> bool:
        """A command to ``rid`` (default: the robot on view, read once)."""
        rid = self.robot_id if rid is None else rid
        if rid is None:
            return False
        try:
            self.actions.command(rid, delta_pos, delta_rot, self._current_gripper(rid))
        except ServiceError as exc:
            if exc.status != 429 or not quiet_429:  # 429: the composed step is full; the next tick takes more
                self._refused(f"Command to robot {rid}", exc)
            return False
        return True

    def _jog_callback(self, pos_axis: int | None, rot_axis: int | None, sign: float):
        def jog(_event) -> None:
            delta_pos, delta_rot = np.zeros(3), np.zeros(3)
            if pos_axis is not None:
                delta_pos[pos_axis] = sign * float(self.step_mm.value) / 1000.0
            if rot_axis is not None:
                delta_rot[rot_axis] = sign * np.radians(float(self.turn_deg.value))
            self._send(delta_pos, delta_rot)

        return jog

    def _set_gripper(self, value: float) -> None:
        previous = self._gripper
        self._gripper = value
        if not self._send(np.zeros(3), np.zeros(3), quiet_429=False):
            self._gripper = previous

    def _toggle_gripper(self) -> None:
        rid = self.robot_id
        if rid is not None:
            self._set_gripper(-1.0 if self._current_gripper(rid) > 0 else 1.0)

    def _on_drag(self, pos: np.ndarray, wxyz: np.ndarray, phase: str) -> None:
        with self._lock:
            self._drag = (pos, wxyz)
            self._dragging = phase != "end"

    # -- the tick (console thread) -------------------------------------------------------------------------
    def tick(self, snap: FleetSnapshot) -> None:
        self._notifications(snap)
        self._heartbeat(snap)
        self._set(self.overview, "content", overview_markdown(snap, self.identity.name))
        self._set(self.lineages, "content", lineage_markdown(snap.lineages))
        self._queue(snap)
        self._follow_state(snap)
        options = tuple(f"{rid} · {v.task}" for rid, v in sorted(snap.robots.items()))
        if self.robot_id is None and snap.robots:
            waiting = [r.robot_id for r in snap.queue if r.holder is None]
            self._select(waiting[0] if waiting else min(snap.robots))
        if self.robot_id not in snap.robots:
            return
        label = next(o for o in options if self._parse_robot(o) == self.robot_id)
        if self._sent.get((id(self.robot_select), "options")) != options:
            self.robot_select.options = options
            self._sent[(id(self.robot_select), "options")] = options
        self._set(self.robot_select, "value", label)
        self._robot(snap)
        if self.takeovers is not None:
            self.takeovers.show(self.robot_id)

    def _follow_state(self, snap: FleetSnapshot) -> None:
        """The line above the tabs: the robot followed while it is under this operator's hands, else what
        the queue puts first. Once the followed robot is handed back (or its episode ended, or its lease
        ran out), back to the fleet: the overview camera. A snapshot taken before the claim does not show
        it yet, and does not end it."""
        me = self.identity.name
        with self._lock:
            following = self._following
        if following is not None:
            rid, since = following
            req = snap.request(rid)
            if snap.now < since or (req is not None and req.holder == me and rid in snap.robots):
                self._set(self.follow_status, "content", f"Following the queue: robot {rid} · R hands it back")
                return
            with self._lock:
                self._following = None
            self.client.camera.position, self.client.camera.look_at = CAMERA_POSITION, CAMERA_LOOK_AT
            self._notify("Back to the fleet", f"Robot {rid} is handed back. T takes the next in the queue.")
        # one short line whatever the queue holds: what is under the pointer below must not move
        head, _ = queue_head(snap.queue, me)
        if head is not None:
            task = snap.robots[head].task if head in snap.robots else "?"
            text = f"Next in the queue: robot {head} ({task}) · T takes it"
        else:
            text = "The queue is empty" if not snap.queue else "Every request in the queue is held by someone else"
        self._set(self.follow_status, "content", text)

    def _set(self, handle, attr: str, value) -> None:
        """Assigns a handle's property only when it changed: only what changed is sent."""
        key = (id(handle), attr)
        if key in self._sent and self._sent[key] == value:
            return
        setattr(handle, attr, value)
        self._sent[key] = value

    def _notifications(self, snap: FleetSnapshot) -> None:
        me = self.identity.name
        requests = {r.robot_id: r for r in snap.queue}
        if self._known_requests is None:  # first tick: what is already there, in one line
            self._known_requests = set(requests)
            if requests:
                self._notify("Assistance queue", f"{len(requests)} robot(s) wait for help", "yellow")
        for rid in sorted(set(requests) - self._known_requests):
            view = snap.robots.get(rid)
            self._notify(f"Robot {rid} asks for help", f"{view.task if view else ''}: {requests[rid].reason}", "yellow")
        self._known_requests = set(requests)
        with self._lock:
            held_now = {rid for rid, r in requests.items() if r.holder == me}
            for rid in sorted(self._held - held_now - self._released):
                view = snap.robots.get(rid)
                if rid in requests or (view is not None and view.mode == Mode.WAITING):
                    self._notify(
                        f"Lease lost on robot {rid}",
                        "Your lease ran out; the robot holds and waits in the queue.",
                        "red",
                    )
            # held robots come from snapshots only (a claim after this tick's snapshot shows up at the next);
            # a hand-back is remembered until the snapshots stop showing the robot as held
            self._held, self._released = held_now, self._released & held_now
        faulted = {rid for rid, v in snap.robots.items() if v.mode == Mode.FAULTED}
        for rid in sorted(faulted - self._faulted):
            self._notify(f"Robot {rid} faulted", snap.robots[rid].fault or "its worker stopped", "red")
        self._faulted = faulted

    def _heartbeat(self, snap: FleetSnapshot) -> None:
        if snap.now - self._last_heartbeat < HEARTBEAT_S:
            return
        self._last_heartbeat = snap.now
        with self._lock:  # only leases this browser took: one held through the API or another tab is theirs
            held = {r.robot_id for r in snap.queue if r.holder == self.identity.name}
            # a claim made after this snapshot was taken is not in it yet: kept until a later snapshot
            self._claimed = {rid: t for rid, t in self._claimed.items() if rid in held or t > snap.now}
            mine = sorted(rid for rid in self._claimed if rid in held)
        for rid in mine:
            with contextlib.suppress(ServiceError):  # the lease ran out or went back: a notification says so
                self.actions.heartbeat(rid)

    def _queue(self, snap: FleetSnapshot) -> None:
        me = self.identity.name
        key = tuple((r.id, r.holder) for r in snap.queue)
        if key != self._queue_key:
            for handles in self._queue_rows.values():
                for h in handles:
                    h.remove()
                    for attr in ("content", "disabled"):  # a new handle may get a removed one's id
                        self._sent.pop((id(h), attr), None)
            self._queue_rows = {}
            with self.queue_folder:
                for req in snap.queue:
                    text = self.client.gui.add_markdown(queue_row(req, snap.robots.get(req.robot_id), snap.now, me))
                    free = req.holder is None or req.holder == me
                    claim = self.client.gui.add_button(
                        f"Claim robot {req.robot_id}", color="orange", disabled=not (free and self.actions.can_operate)
                    )
                    view = self.client.gui.add_button(f"View robot {req.robot_id}")
                    claim.on_click(lambda _, rid=req.robot_id: self._claim(rid))
                    view.on_click(lambda _, rid=req.robot_id: self._select(rid))
                    self._queue_rows[req.id] = (text, claim, view)
            self._queue_key = key
            self._set(self.queue_empty, "visible", not snap.queue)
        for req in snap.queue:
            row = self._queue_rows.get(req.id)
            if row is not None:
                self._set(row[0], "content", queue_row(req, snap.robots.get(req.robot_id), snap.now, me))

    def _robot(self, snap: FleetSnapshot) -> None:
        rid = self.robot_id
        view = snap.robots[rid]
        req = snap.request(rid)
        holding = req is not None and req.holder == self.identity.name and view.mode == Mode.TELEOP
        if view.task not in self._tasks:
            self._tasks[view.task] = make_task(view.task)  # no simulation: it builds one only when stepped
        task = self._tasks[view.task]
        self._set(self.status, "content", robot_markdown(view, req, snap.now, self.identity.name, task))
        can_claim = (
            self.actions.can_operate and req is not None and not holding and (req.holder in (None, self.identity.name))
        )
        self._set(self.claim_button, "disabled", not can_claim)
        self._set(self.release_button, "disabled", not holding)
        for button in (*self.jog_buttons, self.open_button, self.close_button):
            self._set(button, "disabled", not holding)
        key = (rid, view.timeline[-1] if view.timeline else None, len(view.timeline))
        if key != self._timeline_key:
            self.plot.data = timeline_data(view)
            self._timeline_key = key
        self.cameras.show(rid)
        self._scene(view, holding)

    def _scene(self, view, holding: bool) -> None:
        if self.scene is None or (self.scene.robot_id, self.scene.version) != (view.id, view.slot.version):
            self._build_scene(view)  # another robot, or its policy swapped: the field's units come from the policy
            return
        scene = self.scene
        scene.update(view.frame, view.last_result)
        with self._lock:
            frame_now = self._frame_gripper == view.id and view.frame is not None
            if frame_now:
                self._frame_gripper = None
        if frame_now:  # just claimed: the gripper with its field and modes, readable
            self._focus()
        if not holding:
            scene.hide_target()
            self._drag = None
            return
        scene.show_target(self._on_drag)
        with self._lock:
            drag, dragging = self._drag, self._dragging
        if drag is None:
            scene.follow()
            return
        delta_pos, delta_rot = pose_delta(drag[0], drag[1], view.frame)
        if np.linalg.norm(delta_pos) < GIZMO_TOLERANCE[0] and np.linalg.norm(delta_rot) < GIZMO_TOLERANCE[1]:
            if not dragging:
                with self._lock:
                    self._drag = None
            return
        # one command per frame: until the frame that applied the last one arrives, the robot still looks where
        # it was, and sending the same step again would overshoot
        if self._gizmo_sent_t is not None and self._gizmo_sent_t >= (view.id, view.frame.t):
            return
        with self._lock:
            if view.id in self._released:  # handed back since this tick's snapshot
                return
        if self._send(
            _clamp(delta_pos, self.limits.max_delta_pos), _clamp(delta_rot, self.limits.max_delta_rot), rid=view.id
        ):
            self._gizmo_sent_t = (view.id, view.frame.t)

    def _build_scene(self, view) -> None:
        """Builds the robot's scene off the tick (a few seconds); the tick keeps the panel live meanwhile."""
        if self._building is not None and not self._building.done():
            return
        if self.scene is not None:
            self.scene.remove()
            self.scene = None

        def build() -> None:
            started = time.monotonic()
            model = self.models.copy(view.task)
            if self.closed:
                return
            scene = RobotScene(
                self.client, view.id, model, view.slot.policy.action_normalizer, view.slot.version, probe_radius(view)
            )
            self.scene = scene
            log.debug(
                "console: scene of robot %d for %s in %.1f s", view.id, self.identity.name, time.monotonic() - started
            )

        self._building = self.builds.submit(build)


def _clamp(v: np.ndarray, limit: float) -> np.ndarray:
    """``v`` shortened to just under ``limit`` (the per-step limit the service checks)."""
    norm = float(np.linalg.norm(v))
    return v if norm <= limit * 0.98 else v * (limit * 0.98 / norm)

"""Camera views of the robots someone watches: each one's front and wrist cameras, rendered by MuJoCo in a
process of their own (``server.camera_worker``), from the joint positions the robot's last frame carries.

**Only for robots someone watches.** A console shows a robot's cameras by asking for them
(``CameraFeed.view``) at each of its ticks; a robot is rendered while someone asked in the last
``WATCH_TTL_S`` seconds, at ``hz`` (2 by default) and ``width`` x ``height`` (160 x 120), each of its new
frames at most once. Nothing starts until the first robot is watched: a fleet nobody watches pays nothing.

**Rate and size.** Rendering is software OpenGL on the CPU that steps the fleet (OSMesa), so the views
are small and slow (two views per watched robot, 2 Hz) and the process runs at a lower CPU priority than
the fleet; what they cost the fleet is ``hitl bench console``'s to measure. The 3D view stays the live
one (every tick); the camera views show what the robot's cameras see, as an operator of a real robot
works from them.

**When there is no renderer.** If the process cannot start, OpenGL does not come up, or the process dies
or stops answering mid-run, ``view`` says so (``CameraView.reason``, with the end of what the renderer
wrote to stderr) and the feed stays off: the console shows the reason and works without cameras. A robot
whose own views fail (its state does not fit its task's model) says why, and the others go on.

**OpenGL.** The renderer's backend is chosen here, not inherited: ``gl`` (``Settings.cameras.gl``,
``osmesa`` by default) is set as both ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM`` in its environment (the
fleet's own process sets ``MUJOCO_GL`` for robosuite, which would otherwise leak into it).

**A policy that sees.** Where a robot's frames carry its policy's own images of the console's cameras
(``RobotFrame.images``: a policy that sees front and wrist, as lift's), the console shows those, scaled up
for the eye (nearest pixel, square): the operator sees exactly what the policy saw, and nothing is rendered
twice. Other robots (state-based policies, or a policy whose cameras are not the console's) are rendered
as above.

**Recording.** Each view rendered while the robot is under teleop goes to ``on_images``: the fleet writes
it into the open takeover segment (``foxglove.CompressedImage``, ``storage.segments``), so a segment
carries the frames its operator saw.
"""

from __future__ import annotations

import io
import logging
import os
import select
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import msgspec
import numpy as np

from server.camera_worker import HEADER, MAX_MESSAGE
from sim.cameras import CAMERAS, DEFAULT_SIZE
from sim.frame import RobotFrame

log = logging.getLogger("hitl.cameras")

WATCH_TTL_S = 3.0  # a robot stays watched this long after the last ask
READY_TIMEOUT_S = 120.0  # the process imports the simulator before it answers
# a render that takes longer: the renderer is taken as stuck. Generous: a task's first render builds its
# simulation (seconds), and at its lower priority the renderer waits while the fleet keeps the cores busy
ANSWER_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class CameraImages:
    """One frame's camera views: ``images`` camera name (``sim.cameras.CAMERAS``) -> JPEG bytes; ``t`` and
    ``clock`` the frame's; ``rendered_at`` wall-clock seconds."""

    robot_id: int
    t: int
    clock: int | None
    images: dict[str, bytes]
    width: int
    height: int
    rendered_at: float


@dataclass(frozen=True)
class CameraView:
    """What a watcher gets: the robot's latest views (None before the first), or why there are none."""

    available: bool
    reason: str | None = None
    images: CameraImages | None = None
    hz: float = 0.0


FrameOf = Callable[[int], tuple[str, RobotFrame | None]]  # robot id -> (task, its last frame)
STDERR_TAIL = 600  # characters of the renderer's stderr kept in a failure's reason


class CameraFeed:
    def __init__(
        self,
        frame_of: FrameOf,
        on_images: Callable[[CameraImages], None] | None = None,
        hz: float = 2.0,
        size: tuple[int, int] = DEFAULT_SIZE,
        quality: int = 80,
        enabled: bool = True,
        gl: str = "osmesa",
        env: dict[str, str] | None = None,
    ) -> None:
        """frame_of: where each robot's task and last frame come from; on_images: called with each rendered
        view (the fleet records it); enabled: False turns the feed off (``Settings.cameras.enabled``); gl: the
        renderer's OpenGL backend; env: on top of the renderer's environment (tests)."""
        self.frame_of, self.on_images = frame_of, on_images
        self.hz, self.size, self.quality, self.gl, self.env = hz, size, quality, gl, env or {}
        self._lock = threading.Lock()
        self._watched: dict[int, float] = {}  # robot -> watched until (monotonic)
        self._latest: dict[int, CameraImages] = {}
        self._frames: dict[int, RobotFrame] = {}  # the frame each robot's latest views show (a new one is rendered)
        self._errors: dict[int, str] = {}  # robot -> why its last frame could not be rendered
        self._reason: str | None = None if enabled else "camera views are off (settings: cameras.enabled = false)"
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.process: subprocess.Popen | None = None  # the renderer, while it runs (the feed's thread owns it)
        self.rendered = 0  # views rendered (pairs of cameras), for the console's cost

    # -- watchers ------------------------------------------------------------------------------------------------
    def view(self, robot_id: int) -> CameraView:
        """The robot's latest views, and from now on it is watched (see the module)."""
        with self._lock:
            if self._stop.is_set():
                return CameraView(False, "camera views stopped with the service", None, self.hz)
            if self._reason is not None:
                return CameraView(False, self._reason, None, self.hz)
            self._watched[robot_id] = time.monotonic() + WATCH_TTL_S
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="camera-feed", daemon=True)
                self._thread.start()
            if robot_id in self._errors:
                return CameraView(False, f"this robot's views could not be rendered: {self._errors[robot_id]}")
            return CameraView(True, None, self._latest.get(robot_id), self.hz)

    def close(self) -> None:
        """Stops the feed: the renderer is killed, so the feed's thread, if it waits on it, wakes and ends it."""
        with self._lock:
            self._stop.set()
            thread, proc = self._thread, self.process
        if proc is not None:
            proc.kill()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10)

    # -- the renderer (the feed's thread) ----------------------------------------------------------------------------
    def _run(self) -> None:
        with tempfile.TemporaryFile() as stderr:
            try:
                self._serve(stderr)
            finally:
                self._end_process()

    def _serve(self, stderr) -> None:
        try:
            self._spawn(stderr)
        except Exception as exc:  # noqa: BLE001 - any way of not starting is said to the watchers
            self._fail(f"no camera renderer: {exc}", stderr)
            return
        period = 1.0 / self.hz
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                self._round(started)
            except Exception as exc:  # noqa: BLE001 - the renderer died or hangs: off, said
                self._fail(f"the camera renderer failed mid-run: {exc}", stderr)
                return
            self._stop.wait(max(0.0, period - (time.monotonic() - started)))

    def _round(self, now: float) -> None:
        """One render of each watched robot that has a new frame."""
        with self._lock:
            self._watched = {rid: until for rid, until in self._watched.items() if until > now}
            watched, done = list(self._watched), dict(self._frames)
        for rid in watched:
            try:
                task, frame = self.frame_of(rid)
            except Exception:  # noqa: BLE001 - a robot that went away
                continue
            if frame is None or done.get(rid) is frame:
                continue
            if all(name in frame.images for name in CAMERAS):
                images, error = self._policy_views(rid, frame), None
            elif frame.qpos is None:
                continue
            else:
                images, error = self._render(rid, task, frame)
            with self._lock:
                self._frames[rid] = frame  # rendered or not, this frame is not tried again
                if error is not None:
                    if self._errors.get(rid) != error:
                        log.warning("camera views of robot %d: %s", rid, error)
                    self._errors[rid] = error
                    continue
                self._errors.pop(rid, None)
                self._latest[rid] = images
                self.rendered += 1
            if self.on_images is not None:
                try:
                    self.on_images(images)
                except Exception:  # noqa: BLE001 - recording must not stop the views
                    log.exception("camera views of robot %d: recording failed", rid)

    def _fail(self, reason: str, stderr) -> None:
        if self._stop.is_set():  # the feed was closed: nothing failed
            return
        stderr.seek(0)
        tail = stderr.read().decode("utf-8", "replace").strip()[-STDERR_TAIL:]
        reason = f"{reason} (stderr: {tail})" if tail else reason
        log.warning("camera views off: %s", reason)
        with self._lock:
            self._reason = reason
            self._latest.clear()
            self._frames.clear()

    def _end_process(self) -> None:
        with self._lock:
            proc, self.process = self.process, None
        if proc is None:
            return
        try:
            proc.stdin.close()
            proc.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait(timeout=5)
        proc.stdout.close()

    def _spawn(self, stderr) -> None:
        env = os.environ | {"MUJOCO_GL": self.gl, "PYOPENGL_PLATFORM": self.gl} | self.env
        proc = subprocess.Popen(
            [sys.executable, "-m", "server.camera_worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=stderr,
            env=env,
            bufsize=0,
        )
        with self._lock:
            self.process = proc
            stopped = self._stop.is_set()
        if stopped:  # closed while it started: close() did not see it
            proc.kill()
            raise RuntimeError("the feed was closed")
        hello = self._receive(READY_TIMEOUT_S)
        if not hello.get("ready"):
            raise RuntimeError(hello.get("error") or "the renderer did not start")

    def _receive(self, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        (n,) = HEADER.unpack(self._read(HEADER.size, deadline, timeout))
        if n > MAX_MESSAGE:
            raise RuntimeError(f"the renderer sent a message of {n} bytes")
        return msgspec.msgpack.decode(self._read(n, deadline, timeout))

    def _read(self, n: int, deadline: float, timeout: float) -> bytes:
        out = bytearray()
        proc = self.process
        fd = proc.stdout.fileno()
        while len(out) < n:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise RuntimeError(f"the renderer did not answer in {timeout:.0f} s")
            chunk = os.read(fd, n - len(out))
            if not chunk:
                code = proc.wait(timeout=5)
                raise RuntimeError(f"the renderer stopped (exit code {code})")
            out += chunk
        return bytes(out)

    def _policy_views(self, robot_id: int, frame: RobotFrame) -> CameraImages:
        """The policy's own frames of the console's cameras, as JPEG views ``size[1]`` pixels square."""
        from PIL import Image

        side = self.size[1]
        images = {}
        for name in CAMERAS:
            buf = io.BytesIO()
            image = Image.fromarray(frame.images[name], "RGB").resize((side, side), Image.Resampling.NEAREST)
            image.save(buf, format="JPEG", quality=self.quality)
            images[name] = buf.getvalue()
        return CameraImages(robot_id, frame.t, frame.clock, images, side, side, time.time())

    def _render(self, robot_id: int, task: str, frame: RobotFrame) -> tuple[CameraImages | None, str | None]:
        """(views, None), or (None, why) when this request failed and the renderer goes on; raises when the
        renderer itself failed."""
        job = {
            "task": task,
            "qpos": np.asarray(frame.qpos, dtype=np.float64).tobytes(),
            "placed": {name: [*map(float, pos), *map(float, quat)] for name, (pos, quat) in frame.placed.items()},
            "width": self.size[0],
            "height": self.size[1],
            "quality": self.quality,
        }
        body = msgspec.msgpack.encode(job)
        proc = self.process
        try:
            proc.stdin.write(HEADER.pack(len(body)) + body)
        except OSError as exc:
            raise RuntimeError(f"the renderer stopped (exit code {proc.poll()})") from exc
        reply = self._receive(ANSWER_TIMEOUT_S)
        if "error" in reply:
            return None, str(reply["error"])
        images = {name: bytes(reply["images"][name]) for name in CAMERAS}
        return CameraImages(robot_id, frame.t, frame.clock, images, self.size[0], self.size[1], time.time()), None

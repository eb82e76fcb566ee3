"""``RuntimeHost``: the fleet runtime's side of the API processes' connection (``server.runtime``).

The API processes reach the ``Fleet`` through two kinds of connection (``server.runtime.wire``):

- **calls** (claim, heartbeat, command, release, the admin's): one thread per connection here, each
  call answered in turn. They are the ``FleetPort`` members, which never wait for a tick in progress
  (claims and releases go to the handover mailbox, commands to the command mailbox) except the rare
  admin calls; an API process opens a connection per concurrent call, so an admin's pause never holds
  up an operator's command.
- **snapshots**: one thread here publishes, ``publish_hz`` times a second, the robots whose published
  view changed since its last snapshot, the open requests, and once a second the fleet metrics and
  the schedule. Each snapshot is pickled once, however many API processes subscribe. Reads (robot
  list, detail, queue, metrics, the console) are then answered in the API process from its copy,
  without a call here: the runtime's interpreter spends on readers a fixed cost per snapshot, not one
  per request.

The runtime never waits for an API process: a subscriber whose socket does not take a snapshot within
``send_timeout`` seconds is dropped (it reconnects and gets a full snapshot).
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing import connection
from multiprocessing.connection import Connection, Listener

from server.errors import ServiceError
from server.finetune.scheduler import ScheduleStatus
from server.runtime.wire import CALLS, ROBOT_CALLS, Call, Hello, Reply, Snapshot, portable, timeline_since

log = logging.getLogger("hitl.runtime")
SWITCH_INTERVAL_S = 0.001  # the runtime process's (sys.setswitchinterval), set once it serves API processes


class RuntimeHost:
    """Serves ``fleet`` (a ``server.fleet.fleet.Fleet``) to API processes at ``address`` (host, port; port 0:
    a free one, read back from ``address`` once started)."""

    def __init__(
        self,
        fleet,
        authkey: bytes,
        address: tuple[str, int] = ("127.0.0.1", 0),
        publish_hz: float = 20.0,
        schedule: Callable[[], ScheduleStatus] | None = None,
        send_timeout: float = 5.0,
    ) -> None:
        self.fleet, self.authkey, self.publish_hz = fleet, authkey, publish_hz
        self.schedule, self.send_timeout = schedule, send_timeout
        self._listener = Listener(address, family="AF_INET")  # the key is checked per connection (``_open``)
        self._stop = threading.Event()
        self._subscribers: list[Connection] = []
        self._joining: list[Connection] = []
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []

    @property
    def address(self) -> tuple[str, int]:
        return self._listener.address

    def start(self) -> RuntimeHost:
        # A call's thread takes the interpreter a few times (receive, call, answer); at the default 5 ms
        # switch interval each take can wait a whole interval behind the control loop's Python.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        for target, name in ((self._accept, "runtime-accept"), (self._publish, "runtime-publish")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("fleet runtime: serving API processes on %s:%d", *self.address)
        return self

    def stop(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):  # a blocked accept() is not woken by closing its socket: connect
            socket.create_connection(self.address, timeout=1).close()
        self._listener.close()
        for thread in self._threads:
            thread.join(timeout=5)
        with self._lock:
            for conn in self._subscribers + self._joining:
                conn.close()
            self._subscribers.clear()
            self._joining.clear()

    # -- connections ------------------------------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn = self._listener.accept()
            except OSError:  # the listener was closed (stop)
                if self._stop.is_set():
                    return
                continue
            if self._stop.is_set():
                conn.close()
                return
            threading.Thread(target=self._open, args=(conn,), name="runtime-open", daemon=True).start()

    def _open(self, conn: Connection) -> None:
        """The key's challenge both ways, as ``Listener(authkey=...)`` does, but in the connection's own
        thread: a client that never answers holds up no one else. Then its ``Hello``."""
        try:
            connection.deliver_challenge(conn, self.authkey)
            connection.answer_challenge(conn, self.authkey)
            hello = conn.recv()
        except (OSError, EOFError, connection.AuthenticationError, pickle.UnpicklingError) as exc:
            log.warning("fleet runtime: a connection was refused (%s)", type(exc).__name__)
            conn.close()
            return
        if not isinstance(hello, Hello):
            conn.close()
        elif hello.channel == "snapshots":
            _set_send_timeout(conn, self.send_timeout)
            with self._lock:
                self._joining.append(conn)
        else:
            threading.current_thread().name = f"runtime-calls-{hello.who}"
            self._serve(conn)

    def _serve(self, conn: Connection) -> None:
        with conn:
            while not self._stop.is_set():
                try:
                    call = conn.recv()
                except (EOFError, OSError):
                    return
                reply = self._answer(call)
                try:
                    conn.send(reply)
                except OSError:
                    return

    def _answer(self, call) -> Reply:
        if not isinstance(call, Call) or call.method not in CALLS or not isinstance(call.args, tuple):
            return Reply(error=(400, f"not a call the runtime answers: {call!r}"[:200]))
        try:
            value = getattr(self.fleet, call.method)(*call.args)
        except ServiceError as exc:
            return Reply(error=(exc.status, exc.message), t=time.monotonic())
        except Exception:  # noqa: BLE001 - answered as the API answers an unexpected error, and logged here
            log.exception("fleet runtime: %s failed", call.method)
            return Reply(error=(500, f"{call.method} failed in the fleet runtime; see its log"))
        t = time.monotonic()
        view = portable(self.fleet.view(call.args[0])) if call.method in ROBOT_CALLS else None
        return Reply(value=value, t=t, view=view)

    # -- snapshots --------------------------------------------------------------------------------------------
    def _publish(self) -> None:
        period = 1.0 / self.publish_hz
        sent: dict[int, object] = {}  # the view objects in the last snapshot, by robot
        marks: dict[int, tuple] = {}  # where each robot's timeline stood then (``timeline_since``)
        slow_every = max(1, round(self.publish_hz))  # metrics and schedule: once a second
        n = 0
        while not self._stop.wait(period):
            with self._lock:
                joining, self._joining = self._joining, []
            try:
                sent, marks = self._publish_once(sent, marks, joining, n % slow_every == 0)
            except Exception:  # noqa: BLE001 - a snapshot that cannot be built must not end the publishing
                log.exception("fleet runtime: a snapshot failed; the next one is tried")
                for conn in joining:  # they connect again and get a full snapshot then
                    conn.close()
            n += 1

    def _publish_once(self, sent: dict, marks: dict, joining: list[Connection], slow: bool) -> tuple[dict, dict]:
        """One snapshot to the subscribers (the changes) and a full one to those ``joining``; returns the
        views sent and where their timelines stood, for the next."""
        t = time.monotonic()
        views = self.fleet.views()
        robots = tuple(v.id for v in views)
        changed = {v.id: portable(v, self._since(marks, v)) for v in views if sent.get(v.id) is not v}
        requests = self.fleet.requests()
        slow = slow or bool(joining)
        metrics = self.fleet.metrics() if slow else None
        schedule = self.schedule() if slow and self.schedule is not None else None
        ticks = self.fleet.ticks
        if self._subscribers:
            self._send(
                self._subscribers, pickle.dumps(Snapshot(t, ticks, changed, requests, robots, metrics, schedule))
            )
        if joining:
            full = {v.id: portable(v) for v in views}
            blob = pickle.dumps(Snapshot(t, ticks, full, requests, robots, metrics, schedule, full=True))
            self._send(joining, blob)
            with self._lock:
                self._subscribers.extend(c for c in joining if not c.closed)
        return {v.id: v for v in views}, {v.id: timeline_since(v) for v in views}

    @staticmethod
    def _since(marks: dict[int, tuple], view) -> int | None:
        """The clock the robot's timeline tail starts from: the last point sent, in the same episode."""
        episode, last = marks.get(view.id, (None, None))
        return last if last is not None and episode == view.episode_id else None

    def _send(self, conns: list[Connection], blob: bytes) -> None:
        for conn in list(conns):
            try:
                conn.send_bytes(blob)
            except OSError:  # gone, or too slow to take it: it reconnects and starts from a full snapshot
                conn.close()
                with self._lock:
                    if conn in self._subscribers:
                        self._subscribers.remove(conn)


def _set_send_timeout(conn: Connection, seconds: float) -> None:
    """A send that blocks longer than ``seconds`` fails (SO_SNDTIMEO) instead of stalling the publisher;
    the descriptor stays blocking, so a momentarily full buffer only waits."""
    sock = socket.socket(fileno=conn.fileno())
    try:
        whole = int(seconds)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", whole, int((seconds - whole) * 1e6)))
    finally:
        sock.detach()  # the connection keeps its descriptor

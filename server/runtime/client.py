"""``RemoteFleet``: the ``FleetPort`` of an API process whose fleet runtime runs in another process.

Reads (``view``, ``views``, ``requests``, ``metrics``, ``ticks``) come from the last snapshot the
runtime published (``server.runtime.host``: ``publish_hz`` a second, so at most one period old), kept
by a receiver thread; an API request never waits for the runtime to read them. The calls that change
something go to the runtime, each on a connection of its own from a small pool, and their answer
carries the robot's view after the call, which replaces the snapshot's when it was read later
(``server.runtime.wire``): a claimant sees its claim at once.

**Claims across API processes.** Several API processes (replicas) can serve one fleet. Concurrent
claims of a robot are decided in the shared database first: the robot's claim lease
(``server.lease``, one conditional UPDATE, reentrant for its holder) lets exactly one operator
through, whichever replicas the claims arrived at, PostgreSQL or SQLite alike. The runtime then
applies the claim to its queue, which stays the authority on who drives the robot: a claim it refuses
(another operator's takeover is still alive there, or the request ended) gives the database lease
back. The database lease lasts ``lease_seconds`` from the claim and is not renewed by heartbeats
(no database write per heartbeat): it only has to outlive the race between concurrent claims, and it
never outlives the runtime's own lease, which heartbeats and commands renew. A release gives it back.

Policy slots cross as ``SlotRef``s; ``SlotCache`` loads each version once, from the same folder, so
the console in this process draws with the same network and thresholds as the runtime serves.
"""

from __future__ import annotations

import logging
import pickle
import threading
from collections import deque
from dataclasses import replace
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection
from pathlib import Path

from sqlalchemy.orm import sessionmaker

from server import lease, registry
from server.cameras import CameraView
from server.errors import ServiceError
from server.finetune.scheduler import ScheduleStatus
from server.fleet.assistance import AssistanceRequest
from server.fleet.metrics import MetricsReport
from server.fleet.robot import U_HISTORY, RobotView
from server.fleet.slots import PolicySlot, load_slot
from server.runtime.wire import Call, Hello, Reply, SlotRef, Snapshot, TimelineTail
from server.settings import Settings
from sim.spaces import TeleopCommand

log = logging.getLogger("hitl.runtime")


def robot_lease(robot_id: int) -> str:
    """The name of a robot's claim lease in the database (``server.lease``)."""
    return f"robot-claim:{robot_id}"


class RuntimeUnavailable(ServiceError):
    def __init__(self, message: str) -> None:
        super().__init__(503, message)


class SlotCache:
    """Policy versions loaded in this process, by version id, from the folder the runtime names."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._slots: dict[int, PolicySlot] = {}
        self._lock = threading.Lock()

    def resolve(self, ref: SlotRef) -> PolicySlot:
        with self._lock:
            slot = self._slots.get(ref.version)
            if slot is None:
                slot = load_slot(self.settings, Path(ref.path), ref.task, ref.version, ref.lineage)
                self._slots[ref.version] = slot
            return slot


class RemoteFleet:
    """The runtime at ``address`` with ``authkey``; ``sessions``: the shared database (claim leases,
    the registry's lineages). ``start`` waits for the first snapshot."""

    remote = True

    def __init__(
        self,
        settings: Settings,
        address: tuple[str, int],
        authkey: bytes,
        sessions: sessionmaker,
        who: str = "api",
        max_idle: int = 64,
    ) -> None:
        self.settings, self.address, self.authkey, self.sessions, self.who = settings, address, authkey, sessions, who
        self.slots = SlotCache(settings)
        self.max_idle = max_idle
        self._idle: list[Connection] = []
        self._pool_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._views: dict[int, tuple[float, RobotView]] = {}
        self._robots: tuple[int, ...] = ()
        self._requests: list[AssistanceRequest] = []
        self._metrics: MetricsReport | None = None
        self._schedule: ScheduleStatus | None = None
        self._ticks = 0
        self._first = threading.Event()
        self._live = False  # the snapshot feed is up
        self._stop = threading.Event()
        self._receiver: threading.Thread | None = None
        self._feed: Connection | None = None
        self._lineages = registry.LineageCache(sessions)
        self._timelines: dict[int, deque] = {}  # each robot's timeline, rebuilt from the tails

    # -- life -------------------------------------------------------------------------------------------------
    def start(self, timeout: float = 120.0) -> RemoteFleet:
        self._receiver = threading.Thread(target=self._receive, name="runtime-snapshots", daemon=True)
        self._receiver.start()
        if not self._first.wait(timeout):
            self.stop()
            raise RuntimeUnavailable(f"no snapshot from the fleet runtime at {self.address} in {timeout:.0f} s")
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._feed is not None:
            self._feed.close()
        if self._receiver is not None:
            self._receiver.join(timeout=5)
        with self._pool_lock:
            for conn in self._idle:
                conn.close()
            self._idle.clear()

    def _connect(self, channel: str) -> Connection:
        try:
            conn = Client(self.address, family="AF_INET", authkey=self.authkey)
        except (OSError, EOFError, AuthenticationError) as exc:
            where = f"{self.address[0]}:{self.address[1]}"
            raise RuntimeUnavailable(f"the fleet runtime at {where} cannot be reached: {exc}") from exc
        conn.send(Hello(channel, self.who))
        return conn

    def _receive(self) -> None:
        backoff = 0.1
        while not self._stop.is_set():
            try:
                self._feed = self._connect("snapshots")
                while not self._stop.is_set():
                    self._apply(pickle.loads(self._feed.recv_bytes()))
                    backoff = 0.1
            except Exception as exc:  # noqa: BLE001 - stop() closes the feed under recv(): any error then ends it
                self._live = False
                if self._stop.is_set():
                    return
                if not isinstance(exc, (OSError, EOFError, ServiceError)):
                    log.exception("fleet runtime: a snapshot could not be applied; reconnecting")
                else:
                    log.warning("fleet runtime: snapshot feed lost (%s); reconnecting", exc)
            self._stop.wait(backoff)
            backoff = min(2.0, backoff * 2)

    def _apply(self, snap: Snapshot) -> None:
        # policy versions are loaded before the snapshot is shown: readers never see an unresolved slot
        slots = {rid: self.slots.resolve(v.slot) for rid, v in snap.views.items()}
        with self._state_lock:
            views = {rid: self._local(v, slots[rid]) for rid, v in snap.views.items()}
            if snap.full:
                self._views = {rid: v for rid, v in self._views.items() if rid in snap.robots}
            for rid, view in views.items():
                self._keep(rid, snap.t, view)
            self._robots, self._requests, self._ticks = snap.robots, snap.requests, snap.ticks
            if snap.metrics is not None:
                self._metrics = snap.metrics
            if snap.schedule is not None:
                self._schedule = snap.schedule
        self._live = True
        self._first.set()

    def _local(self, view: RobotView, slot: PolicySlot) -> RobotView:
        """A view as it crossed, with its policy ``slot`` (loaded here) and its timeline rebuilt from the
        tail (under the state lock: the robot's timeline is shared by snapshots and replies)."""
        tail: TimelineTail = view.timeline
        line = self._timelines.get(view.id)
        if line is None or tail.whole:
            line = self._timelines[view.id] = deque(maxlen=U_HISTORY)
        elif tail.points:
            first = tail.points[0].t
            while line and line[-1].t >= first:  # the last point sent may have changed since
                line.pop()
        line.extend(tail.points)
        return replace(view, slot=slot, timeline=tuple(line))

    def _keep(self, rid: int, t: float, view: RobotView) -> None:
        held = self._views.get(rid)
        if held is None or held[0] <= t:
            self._views[rid] = (t, view)

    # -- reads (the last snapshot) ----------------------------------------------------------------------------
    @property
    def ticks(self) -> int:
        """The runtime's, as of its last snapshot; 0 while its snapshot feed is down (``/readyz`` then says
        this API process is not ready)."""
        return self._ticks if self._live else 0

    @property
    def data_dir(self) -> Path:
        return self.settings.data_dir

    def view(self, robot_id: int) -> RobotView:
        held = self._views.get(robot_id)
        if held is None or robot_id not in self._robots:
            raise ServiceError(404, f"no robot {robot_id}")
        return held[1]

    def views(self) -> list[RobotView]:
        views = self._views
        return [views[i][1] for i in sorted(self._robots) if i in views]

    def requests(self) -> list[AssistanceRequest]:
        return list(self._requests)

    def metrics(self) -> MetricsReport:
        if (m := self._metrics) is None:  # a snapshot that joins the feed always carries them
            raise ServiceError(503, "the fleet runtime has not sent its metrics yet")
        return m

    def schedule_status(self) -> ScheduleStatus | None:
        """The runtime's nightly schedule and the jobs it started, as of its last report (once a second)."""
        return self._schedule

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]:
        return self._lineages.get(max_age)

    # -- calls (to the runtime) -------------------------------------------------------------------------------
    def _call(self, method: str, *args):
        with self._pool_lock:
            conn = self._idle.pop() if self._idle else None
        if conn is None:
            conn = self._connect("calls")
        try:
            conn.send(Call(method, args))
            reply: Reply = conn.recv()
        except (OSError, EOFError) as exc:
            conn.close()
            raise RuntimeUnavailable(f"the fleet runtime did not answer {method}: {exc}") from exc
        with self._pool_lock:
            if len(self._idle) < self.max_idle:
                self._idle.append(conn)
            else:
                conn.close()
        if reply.view is not None:
            slot = self.slots.resolve(reply.view.slot)
            with self._state_lock:
                self._keep(reply.view.id, reply.t, self._local(reply.view, slot))
        if reply.error is not None:
            raise ServiceError(*reply.error)
        return reply.value

    def camera_view(self, robot_id: int) -> CameraView:
        """From the runtime, which renders them (``server.cameras``): a round trip per call, bytes only when a
        robot is watched."""
        return self._call("camera_view", robot_id)

    def claim(self, robot_id: int, operator: str) -> AssistanceRequest:
        self.view(robot_id)  # 404 before a lease for a robot that does not exist
        held = lease.acquire(
            self.sessions, robot_lease(robot_id), operator, self.settings.queue.lease_seconds, reentrant=True
        )
        if held is None:
            raise ServiceError(409, f"robot {robot_id} is already controlled by another operator")
        try:
            return self._call("claim", robot_id, operator)
        except ServiceError:
            lease.release(self.sessions, held)
            raise

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest:
        return self._call("heartbeat", robot_id, operator)

    def command(self, robot_id: int, operator: str, command: TeleopCommand) -> int:
        return self._call("command", robot_id, operator, command)

    def release(self, robot_id: int, operator: str) -> None:
        self._call("release", robot_id, operator)
        # the claim lease, if this operator's still runs: the next claim need not wait for it to lapse
        held = lease.acquire(self.sessions, robot_lease(robot_id), operator, self.settings.queue.lease_seconds, True)
        if held is not None:
            lease.release(self.sessions, held)

    def pause(self, robot_id: int) -> None:
        self._call("pause", robot_id)

    def resume(self, robot_id: int) -> None:
        self._call("resume", robot_id)

    def reset(self, robot_id: int) -> None:
        self._call("reset", robot_id)

    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int:
        return self._call("register_policy", Path(path).resolve(), task, parent)

    def activate_policy(self, version: int, reason: str | None = None) -> None:
        self._call("activate_policy", version, reason)

"""The operator console: a viser server on an internal 127.0.0.1 port, one ``OperatorPanel`` per browser.

``Console`` is built in the service's lifespan with the fleet. Browsers reach it only through the
service's WebSocket proxy (``web.pages``), which adds a signed identity to each handshake;
a connection without a valid one is closed before it gets anything but the theme. Nothing is added to
viser's shared (server-level) scene or GUI: every browser has its own panel and scene, rebuilt when it
reconnects. One thread ticks at the control rate: it snapshots the fleet once (``FleetSnapshot``) and
sends each browser what changed as one atomic frame.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import viser
from sqlalchemy.orm import sessionmaker

from server.port import FleetPort
from web.identity import HEADER, Identity, IdentitySigner
from web.operator_panel import OperatorPanel
from web.panels import FleetSnapshot
from web.scene import SceneModels
from web.takeovers import TakeoverBoard
from web.viser_internals import close_client, handshake_headers, on_handshake, quiet, remove_share_handlers

log = logging.getLogger("hitl.console")

DEFAULT_HZ = 10.0  # when the fleet free-runs (control_hz = 0)
TITLE = "hitl operator console"


@dataclass
class ConsoleStats:
    ticks: int = 0
    tick_cpu_s: float = 0.0  # CPU time the tick thread spent building and sending updates
    frames_sent: int = 0  # atomic frames sent to browsers (one per browser per tick)


class Console:
    def __init__(
        self,
        fleet: FleetPort,
        hz: float,
        signer: IdentitySigner | None = None,
        models: SceneModels | None = None,
        sessions: sessionmaker | None = None,
    ):
        """sessions: the service's database, for the robot's recent takeovers and their labels (None: the
        console shows none)."""
        self.fleet = fleet
        self.board = TakeoverBoard(sessions) if sessions is not None else None
        self.hz = hz if hz > 0 else DEFAULT_HZ
        self.signer = signer or IdentitySigner()
        self.models = models or SceneModels()
        self.stats = ConsoleStats()
        self.server: viser.ViserServer | None = None
        self._panels: dict[int, OperatorPanel] = {}
        self._identities: dict[int, Identity] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._builds = ThreadPoolExecutor(max_workers=1, thread_name_prefix="console-scene")

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> None:
        # port 0: the OS picks a free ephemeral port (viser would otherwise take 8080 or the next free one)
        with quiet():
            server = viser.ViserServer(host="127.0.0.1", port=0, label=TITLE, verbose=False)
        remove_share_handlers(server)
        server.gui.configure_theme(
            titlebar_content=None,
            control_width="large",
            dark_mode=False,
            show_logo=False,
            show_share_button=False,
        )
        on_handshake(server, self._handshake, self._hangup)
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        self.server = server
        self._thread = threading.Thread(target=self._run, name="console-tick", daemon=True)
        self._thread.start()
        log.info("console: viser on 127.0.0.1:%d (internal; browsers use /console/)", self.port)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._builds.shutdown(wait=False, cancel_futures=True)
        if self.server is not None:
            with quiet():
                self.server.stop()

    @property
    def port(self) -> int:
        return self.server.get_port() if self.server is not None else 0

    @property
    def upstream_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def sign(self, name: str, role: str) -> dict[str, str]:
        """The handshake headers the proxy sends upstream for a logged-in user."""
        return {HEADER: self.signer.sign(Identity(name, role))}

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._panels)

    def viewed(self) -> list[int | None]:
        """The robot each connected browser's panel shows (None: none yet)."""
        with self._lock:
            return [panel.robot_id for panel in self._panels.values()]

    # -- connections ---------------------------------------------------------------------------------
    def _handshake(self, client_id: int) -> None:
        try:  # runs inside viser's connection handler: nothing may escape it
            identity = self.signer.verify(handshake_headers(self.server, client_id).get(HEADER))
        except Exception:
            log.exception("console: could not read connection %d's identity", client_id)
            identity = None
        if identity is None:
            log.warning("console: closed connection %d without a valid signed identity", client_id)
            close_client(self.server, client_id, "no valid identity: connect through the service's /console")
            return
        with self._lock:
            self._identities[client_id] = identity

    def _hangup(self, client_id: int) -> None:
        with self._lock:
            self._identities.pop(client_id, None)
            panel = self._panels.pop(client_id, None)
        if panel is not None:
            panel.closed = True

    def _connect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            identity = self._identities.get(client.client_id)
        if identity is None:
            return
        panel = OperatorPanel(client, identity, self.fleet, self.models, self._builds, self.hz, self.board)
        with self._lock:  # the browser may have gone while its panel was being built
            if client.client_id in self._identities:
                self._panels[client.client_id] = panel
            else:
                panel.closed = True
                return
        log.info("console: %s (%s) connected", identity.name, identity.role)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._identities.pop(client.client_id, None)
            panel = self._panels.pop(client.client_id, None)
        if panel is not None:
            panel.closed = True
            log.info("console: %s disconnected (a lease they held runs out by itself)", panel.identity.name)

    # -- the tick ---------------------------------------------------------------------------------------
    def snapshot(self) -> FleetSnapshot:
        now = time.monotonic()  # before the reads: a claim made after ``now`` may be missing from them
        return FleetSnapshot(
            {v.id: v for v in self.fleet.views()}, tuple(self.fleet.requests()), now, self.fleet.lineages()
        )

    def _run(self) -> None:
        period = 1.0 / self.hz
        next_at = time.monotonic()
        while not self._stop.is_set():
            next_at += period
            cpu = time.thread_time()
            with self._lock:
                panels = list(self._panels.values())
            if panels:
                snapshot = self.snapshot()
                for panel in panels:
                    try:
                        with panel.client.atomic():
                            panel.tick(snapshot)
                        self.stats.frames_sent += 1
                    except Exception:  # one browser's failure never stops the others'
                        log.exception("console: update for %s failed", panel.identity.name)
            self.stats.ticks += 1
            self.stats.tick_cpu_s += time.thread_time() - cpu
            delay = next_at - time.monotonic()
            if delay < -period:  # fell behind: skip, never burst
                next_at = time.monotonic()
            self._stop.wait(max(0.0, delay))

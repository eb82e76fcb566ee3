"""The service with its API apart from the control loop: one fleet runtime, N API processes.

``hitl serve`` with ``api_workers = N`` (N >= 1) runs ``ReplicatedService``:

- this process runs the fleet runtime (``server.runtime.local.FleetRuntime``: the control loop,
  controller, recording, workers, the nightly job's schedule) and serves it to the API processes
  (``server.runtime.host.RuntimeHost``, on 127.0.0.1, with a key made at start);
- N API processes (``ApiReplicas``) each run the FastAPI app and the operator console under uvicorn,
  on the service's one listening socket (the kernel spreads connections among them, as uvicorn's
  ``--workers`` does), or each on a socket of its own behind a load balancer (``separate_ports``). They
  reach the fleet only through ``server.runtime.client.RemoteFleet`` and share the database, which
  decides concurrent claims (``server.lease``). A replica that dies is started again.

The runtime's interpreter then runs the loop and nothing of HTTP: no request parsing, JSON, WebSocket
compression or token checks compete with a tick for its GIL.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import secrets
import signal
import socket
import threading
import time
from pathlib import Path

from server.runtime.host import RuntimeHost
from server.runtime.local import FleetRuntime
from server.runtime.wire import RuntimeLink
from server.settings import Settings

log = logging.getLogger("hitl.runtime")
RESTART_DELAY_S = 1.0


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket (IPPROTO_TCP: asyncio then sets TCP_NODELAY on its connections)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def _serve_replica(settings_json: str, link: RuntimeLink, sock: socket.socket, log_level: str, log_file) -> None:
    """An API process: the app on a ``RemoteFleet`` under uvicorn, on ``sock``. Ends on SIGTERM or SIGINT."""
    import torch
    import uvicorn

    from service.app import create_app

    handlers = [logging.FileHandler(log_file)] if log_file else None
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s", handlers=handlers
    )
    torch.set_num_threads(1)
    threading.Thread(target=_end_with_parent, args=(os.getppid(),), name="parent-watch", daemon=True).start()
    settings = Settings.model_validate_json(settings_json)
    app = create_app(settings, link=link)
    server = uvicorn.Server(uvicorn.Config(app, log_level=log_level, log_config=None))
    app.state.server = server
    server.run(sockets=[sock])


def _end_with_parent(parent: int, poll_s: float = 1.0) -> None:
    """An API process outlives no runtime: when the process that started it is gone (killed, even with
    SIGKILL), it shuts down as on SIGTERM and frees the service's port."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    logging.getLogger("hitl.runtime").warning("the fleet runtime's process %d is gone: stopping", parent)
    os.kill(os.getpid(), signal.SIGTERM)


class ApiReplicas:
    """``len(sockets)`` API processes when ``per_socket``, else ``workers`` processes on ``sockets[0]``."""

    def __init__(
        self,
        settings: Settings,
        link: RuntimeLink,
        sockets: list[socket.socket],
        workers: int,
        log_level: str = "info",
        log_file: Path | None = None,
    ) -> None:
        self.settings_json = settings.model_dump_json()
        self.link, self.log_level, self.log_file = link, log_level, log_file
        self.sockets = sockets if len(sockets) > 1 else sockets * workers
        self.processes: list[mp.process.BaseProcess | None] = [None] * len(self.sockets)
        self.restarts = 0
        self._ctx = mp.get_context("spawn")
        self._stop = threading.Event()
        self._watcher: threading.Thread | None = None

    def _spawn(self, i: int) -> None:
        args = (self.settings_json, self.link, self.sockets[i], self.log_level, self.log_file)
        proc = self._ctx.Process(target=_serve_replica, args=args, name=f"hitl-api-{i}", daemon=False)
        proc.start()
        self.processes[i] = proc

    def start(self) -> ApiReplicas:
        for i in range(len(self.sockets)):
            self._spawn(i)
        self._watcher = threading.Thread(target=self._watch, name="api-replicas", daemon=True)
        self._watcher.start()
        return self

    def _watch(self) -> None:
        while not self._stop.wait(RESTART_DELAY_S):
            for i, proc in enumerate(self.processes):
                if proc is not None and not proc.is_alive() and not self._stop.is_set():
                    log.warning("API process %d (pid %s) ended with %s; starting it again", i, proc.pid, proc.exitcode)
                    self.restarts += 1
                    self._spawn(i)

    def pids(self) -> list[int]:
        return [p.pid for p in self.processes if p is not None and p.is_alive()]

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        if self._watcher is not None:
            self._watcher.join(timeout=5)
        for proc in self.processes:
            if proc is not None and proc.is_alive():
                proc.terminate()  # SIGTERM: uvicorn finishes its requests and runs the app's shutdown
        deadline = time.monotonic() + timeout
        for proc in self.processes:
            if proc is not None:
                proc.join(max(0.1, deadline - time.monotonic()))
                if proc.is_alive():
                    proc.kill()
                    proc.join()


class ReplicatedService:
    """The fleet runtime here and ``workers`` API processes: on ``settings.host:settings.port`` together,
    or, with ``separate_ports``, each on a free port of its own (``urls``)."""

    def __init__(
        self,
        settings: Settings,
        workers: int,
        separate_ports: bool = False,
        log_level: str = "info",
        log_file: Path | None = None,
    ) -> None:
        if workers < 1:
            raise ValueError(f"an API apart from the runtime needs at least 1 API process, got {workers}")
        self.settings, self.workers, self.separate_ports = settings, workers, separate_ports
        self.log_level, self.log_file = log_level, log_file
        self.runtime: FleetRuntime | None = None
        self.host: RuntimeHost | None = None
        self.replicas: ApiReplicas | None = None
        self.sockets: list[socket.socket] = []

    @property
    def fleet(self):
        return self.runtime.fleet

    @property
    def urls(self) -> list[str]:
        out = []
        for sock in self.sockets:
            host, port = sock.getsockname()[:2]
            host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
            out.append(f"http://{f'[{host}]' if ':' in host else host}:{port}")
        return out

    def __enter__(self) -> ReplicatedService:
        try:
            self.runtime = FleetRuntime(self.settings).open()
            self.runtime.start()
            link_key = secrets.token_bytes(32)
            self.host = RuntimeHost(
                self.runtime.fleet,
                link_key,
                publish_hz=2 * max(self.settings.control_hz, 10.0),
                schedule=self.runtime.schedule_status,
            ).start()
            if self.separate_ports:
                self.sockets = [bind(self.settings.host, 0) for _ in range(self.workers)]
            else:
                self.sockets = [bind(self.settings.host, self.settings.port)]
            link = RuntimeLink(self.host.address, link_key)
            self.replicas = ApiReplicas(
                self.settings, link, self.sockets, self.workers, self.log_level, self.log_file
            ).start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self.replicas is not None:
            self.replicas.stop()
        if self.host is not None:
            self.host.stop()
        if self.runtime is not None:
            self.runtime.stop()
        for sock in self.sockets:
            sock.close()

    def wait_ready(self, timeout: float = 300.0) -> None:
        """Until every URL answers ``/readyz`` with 200 (each API process has the runtime's first snapshot
        and the loop has ticked); RuntimeError naming what is missing otherwise."""
        import httpx

        deadline = time.monotonic() + timeout
        pending = list(self.urls)
        while pending and time.monotonic() < deadline:
            for url in list(pending):
                with contextlib.suppress(httpx.HTTPError):
                    if httpx.get(url + "/readyz", timeout=5).status_code == 200:
                        pending.remove(url)
            if pending:
                time.sleep(0.2)
        if pending:
            raise RuntimeError(f"API process(es) at {', '.join(pending)} not ready after {timeout:.0f} s")


def serve(settings: Settings, workers: int, log_level: str = "info") -> int:
    """``hitl serve`` with ``api_workers``: runs until SIGINT or SIGTERM."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with ReplicatedService(settings, workers, log_level=log_level) as service:
        log.info(
            "fleet runtime in process %d; %d API process(es) at %s (pids %s)",
            os.getpid(),
            workers,
            service.urls[0],
            ", ".join(map(str, service.replicas.pids())),
        )
        stop.wait()
        log.info("stopping: API processes first, then the fleet")
    return 0

"""``create_app(settings)`` under uvicorn in a thread of this process, on a free 127.0.0.1 port, its log
in a file: the benchmarks and ``hitl docs screenshots`` run the real service this way, and can read
the services its lifespan built (``app.state``)."""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from pathlib import Path


class _LogCount(logging.FileHandler):
    """The server's log, to a file; counts warnings and errors and keeps the first few."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.warnings, self.first = 0, []

    def emit(self, record: logging.LogRecord) -> None:
        super().emit(record)
        if record.levelno >= logging.WARNING:
            self.warnings += 1
            if len(self.first) < 5:
                self.first.append(f"{record.levelname} {record.name}: {record.getMessage()}"[:300])


class LocalService:
    """``create_app(settings)`` under uvicorn, in a thread, on a socket bound to a free port."""

    def __init__(self, settings, log_path: Path) -> None:
        import uvicorn

        from server.app import RedactTokens, create_app

        # IPPROTO_TCP explicitly: asyncio sets TCP_NODELAY only on sockets whose ``proto`` says TCP (as
        # uvicorn's own, from getaddrinfo); with proto 0 every response would wait out Nagle + delayed ACK
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.app = create_app(settings)
        self.log = _LogCount(log_path)
        self._redact = RedactTokens()
        self._loggers = [logging.getLogger(n) for n in ("uvicorn", "hitl")]
        self._saved = [(lg, lg.propagate, lg.level) for lg in self._loggers]
        for lg in self._loggers:
            lg.addHandler(self.log)
            lg.propagate = False
            lg.setLevel(logging.INFO)
        logging.getLogger("uvicorn.access").addFilter(self._redact)
        config = uvicorn.Config(self.app, log_config=None, log_level="info", access_log=True)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self):
        import httpx

        self.thread.start()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and self.thread.is_alive():
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(self.url + "/readyz").status_code == 200:
                    return self
            time.sleep(0.2)
        self.__exit__()
        tail = Path(self.log.baseFilename).read_text()[-2000:]
        raise RuntimeError(f"the service did not become ready; the end of its log:\n{tail}")

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)
        self.sock.close()
        logging.getLogger("uvicorn.access").removeFilter(self._redact)
        for lg, propagate, level in self._saved:
            lg.removeHandler(self.log)
            lg.propagate, lg.level = propagate, level
        self.log.close()

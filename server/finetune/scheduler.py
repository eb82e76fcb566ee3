"""The nightly fine-tuning job inside ``hitl serve``: a cron schedule and the process it starts.

``Scheduler`` evaluates a cron expression (croniter) on an injectable clock; a thread wakes at most
every ``poll`` seconds and fires once per due time (a time missed while the service was down is not
caught up, as with cron). ``JobLauncher`` starts ``hitl finetune`` as a separate process at low CPU
priority (``os.nice``), so the job's training and evaluation never take the fleet's cores first;
its output goes to ``<data_dir>/logs/``. The database lease decides whether a job actually runs: a
launch while another job (from here, system cron or a Kubernetes CronJob) holds it exits with 3.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path

from croniter import croniter

log = logging.getLogger("hitl.scheduler")


def parse_cron(expr: str) -> str:
    """The expression if it has cron's five fields (minute first; as system cron and Kubernetes take
    them, so the same line works in all three) and croniter accepts it, else ValueError."""
    if not isinstance(expr, str) or len(expr.split()) != 5 or not croniter.is_valid(expr.strip()):
        raise ValueError(f"invalid cron expression {expr!r}: expected five fields, e.g. '0 3 * * *' (03:00 daily)")
    return expr.strip()


def local_now() -> datetime:
    return datetime.now().astimezone()


class FileClock:
    """A clock read from a file holding one ISO 8601 time (``[finetune] clock_file``): a benchmark
    (``hitl bench nights``) or a test moves the night forward by writing the file, and the service's own
    scheduler fires, as it would at that hour. A time without a zone is local time. Unreadable at the
    start: ValueError; unreadable later (mid-write): the last time read, with a warning."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.last = self._read()

    def _read(self) -> datetime:
        try:
            text = self.path.read_text().strip()
        except OSError as exc:
            raise ValueError(f"clock file {self.path}: cannot be read ({exc.strerror})") from None
        try:
            when = datetime.fromisoformat(text)
        except ValueError:
            raise ValueError(f"clock file {self.path}: {text[:40]!r} is not an ISO 8601 time") from None
        return when if when.tzinfo is not None else when.astimezone()

    def __call__(self) -> datetime:
        try:
            self.last = self._read()
        except ValueError as exc:
            log.warning("%s; keeping %s", exc, self.last.isoformat())
        return self.last


def write_clock(path: str | Path, when: datetime) -> None:
    """Sets a ``FileClock``'s time, atomically (the scheduler never reads half a line)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(when.isoformat() + "\n")
    os.replace(tmp, path)


def next_due(expr: str, now: datetime) -> datetime:
    """The first time after ``now`` that the cron expression names."""
    return croniter(parse_cron(expr), now).get_next(datetime)


class Scheduler:
    """Calls ``fire(due_time)`` at each time the cron expression names; ``tick(now)`` is the whole logic
    (tests drive it with their own clock)."""

    def __init__(
        self,
        expr: str,
        fire: Callable[[datetime], None],
        clock: Callable[[], datetime] = local_now,
        poll: float = 30.0,
    ) -> None:
        self.expr = parse_cron(expr)
        self.fire, self.clock, self.poll = fire, clock, poll
        self.next_due = self._after(clock())
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _after(self, when: datetime) -> datetime:
        return next_due(self.expr, when)

    def tick(self, now: datetime | None = None) -> bool:
        """Fires if the next due time has come; True if it fired."""
        now = now or self.clock()
        if now < self.next_due:
            return False
        due, self.next_due = self.next_due, self._after(now)
        try:
            self.fire(due)
        except Exception:  # noqa: BLE001 - a failed launch must not stop later ones
            log.exception("scheduled job at %s could not start", due.isoformat())
        return True

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="finetune-scheduler", daemon=True)
        self._thread.start()
        log.info("fine-tuning scheduled by %r; next run %s", self.expr, self.next_due.isoformat(timespec="minutes"))

    def _run(self) -> None:
        while True:
            wait = max(0.0, min(self.poll, (self.next_due - self.clock()).total_seconds()))
            if self._stop.wait(wait):
                return
            self.tick()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)


class JobLauncher:
    """Starts ``hitl finetune`` processes for the service (schedule and API trigger), one at a time from
    here, with the service's data folder, database and ``[finetune]`` settings (passed as
    ``HITL_FINETUNE``); ``stop`` ends a running one with SIGTERM (it records itself interrupted and
    resumes later)."""

    def __init__(self, data_dir: Path, database_url: str, settings) -> None:
        self.data_dir, self.database_url = Path(data_dir).resolve(), database_url
        self.settings = settings  # server.settings.FinetuneSettings
        self.process: subprocess.Popen | None = None
        self.launches = 0  # processes started from here
        self.last_exit_code: int | None = None  # of the last one that ended
        self._lock = threading.Lock()

    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def launch(
        self,
        trigger: str,
        policy: str | None = None,
        job_id: int | None = None,
        extra: list[str] | None = None,
        on_exit: Callable[[int, Path], None] | None = None,
    ) -> subprocess.Popen | None:
        """The new process, or None when one started from here is still running; ``on_exit(returncode,
        log file)`` is called from a thread when it ends."""
        with self._lock:
            if self.running():
                log.warning("a fine-tuning job started by this service is still running: not starting another")
                return None
            cmd = [sys.executable, "-m", "hitl.cli", "finetune", "--quiet", "--trigger", trigger]
            cmd += ["--data-dir", str(self.data_dir)]  # the database URL goes by environment: it may hold a password
            # the child lowers its own priority: no preexec_fn in a threaded server
            cmd += ["--nice", str(self.settings.niceness)] + (
                ["--idle-priority"] if self.settings.idle_priority else []
            )
            if policy:
                cmd += ["--policy", policy]
            if job_id is not None:
                cmd += ["--job", str(job_id)]
            cmd += extra or []
            logs = self.data_dir / "logs"
            logs.mkdir(parents=True, exist_ok=True)
            stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
            out = open(logs / f"finetune-{stamp}-{trigger}.log", "ab")  # noqa: SIM115 - the child owns it
            env = {**os.environ, "PYTHONUNBUFFERED": "1", "HITL_FINETUNE": self.settings.model_dump_json()}
            env["HITL_DATABASE_URL"] = self.database_url
            try:
                self.process = subprocess.Popen(
                    cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env
                )
            finally:
                out.close()
            log.info("fine-tuning job started (%s), pid %d, log %s", trigger, self.process.pid, out.name)
            self.launches += 1
            self.last_exit_code = None
            proc, path = self.process, Path(out.name)

            def ended() -> None:
                code = proc.wait()
                self.last_exit_code = code
                if on_exit is not None:
                    on_exit(code, path)

            threading.Thread(target=ended, name="finetune-exit", daemon=True).start()
            return self.process

    def stop(self, timeout: float = 30.0) -> None:
        with self._lock:
            if self.running():
                self.process.terminate()
                try:
                    self.process.wait(timeout)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()


@dataclass(frozen=True)
class ScheduleStatus:
    """The nightly job's schedule and the job processes a service started (``GET /finetune-schedule``)."""

    schedule: str | None
    next_run: datetime | None
    clock: str
    running: bool
    launches: int
    last_exit_code: int | None

    @classmethod
    def of(cls, scheduler: Scheduler | None, launcher: JobLauncher) -> ScheduleStatus:
        return cls(
            schedule=scheduler.expr if scheduler is not None else None,
            next_run=scheduler.next_due if scheduler is not None else None,
            clock="file" if launcher.settings.clock_file is not None else "system",
            running=launcher.running(),
            launches=launcher.launches,
            last_exit_code=launcher.last_exit_code,
        )

    def with_launcher(self, launcher: JobLauncher) -> ScheduleStatus:
        """This status (the runtime's) with the jobs ``launcher`` (an API process's) started added."""
        return replace(
            self,
            running=self.running or launcher.running(),
            launches=self.launches + launcher.launches,
            last_exit_code=launcher.last_exit_code if launcher.last_exit_code is not None else self.last_exit_code,
        )

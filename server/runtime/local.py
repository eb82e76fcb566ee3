"""``FleetRuntime``: the fleet runtime of one service, in the process that runs it.

It is what runs once per fleet, whatever serves the API: migrations, recovery of what a crash left
open, the ``Fleet`` (control loop, controller, recording, workers) and the nightly job's scheduler and
launcher. ``hitl serve`` runs it in the API's own process (``api_workers = 0``, the embedded default)
or in a process of its own that API processes reach through ``server.runtime.host`` (``api_workers``
> 0, ``service.replicas``).

Two words, two things: the *fleet* is ``server.fleet.fleet.Fleet`` (the robots, the control loop, the
operators' actions); the *fleet runtime* is this class, the fleet with what runs once per service
around it.
"""

from __future__ import annotations

import logging

from sqlalchemy.engine import Engine
from sqlalchemy.orm import sessionmaker

from server.db import make_engine, migrate, session_factory
from server.finetune.scheduler import FileClock, JobLauncher, Scheduler, ScheduleStatus, local_now
from server.fleet.fleet import Fleet
from server.fleet.recording import recover
from server.settings import Settings

log = logging.getLogger("hitl.server")


class FleetRuntime:
    """``open`` (migrate, recover, build the fleet: nothing runs yet), ``start`` (the control loop and the
    schedule), ``stop`` (the job in progress, then the fleet). ``fleet``, ``sessions`` and ``launcher``
    exist once open."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.engine: Engine | None = None
        self.sessions: sessionmaker | None = None
        self.fleet: Fleet | None = None
        self.launcher: JobLauncher | None = None
        self.scheduler: Scheduler | None = None

    def open(self) -> FleetRuntime:
        settings = self.settings
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        migrate(settings.db_url)
        self.engine = make_engine(settings.db_url)
        self.sessions = session_factory(self.engine)
        found = recover(self.sessions, settings.data_dir)  # before any robot runs
        if found.segments or found.episodes:
            log.info(
                "after a crash: %d takeover segment(s) rewritten as complete MCAP files, %d episode(s) closed as "
                "interrupted (%d file(s) unreadable)",
                found.segments,
                found.episodes,
                found.unreadable,
            )
        self.fleet = Fleet(settings, self.sessions)
        self.launcher = JobLauncher(settings.data_dir, settings.db_url, settings.finetune)
        return self

    def start(self) -> None:
        self.fleet.start()
        log.info("fleet of %d robot(s) started; ready once its control loop has ticked", len(self.fleet.robots))
        finetune = self.settings.finetune
        if finetune.schedule:
            clock_file = finetune.clock_file  # a benchmark's night, else the system clock
            self.scheduler = Scheduler(
                finetune.schedule,
                lambda due: self.launcher.launch("schedule"),
                clock=FileClock(clock_file) if clock_file is not None else local_now,
                poll=1.0 if clock_file is not None else 30.0,
            )
            self.scheduler.start()

    def schedule_status(self) -> ScheduleStatus:
        return ScheduleStatus.of(self.scheduler, self.launcher)

    def stop(self) -> None:
        if self.scheduler is not None:
            self.scheduler.stop()
        if self.launcher is not None:
            self.launcher.stop()  # a job in progress records itself interrupted and resumes next time
        if self.fleet is not None:
            self.fleet.stop()
        if self.engine is not None:
            self.engine.dispose()

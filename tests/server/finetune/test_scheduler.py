"""The fine-tuning schedule on a controlled clock, and its validation in the settings."""

import time
from datetime import datetime, timedelta, timezone

import pytest
from pydantic import ValidationError

from server.finetune.scheduler import Scheduler, parse_cron
from server.settings import Settings

TZ = timezone(timedelta(hours=1))


class Clock:
    def __init__(self, t: datetime) -> None:
        self.t = t

    def __call__(self) -> datetime:
        return self.t


def test_the_nightly_job_fires_once_per_due_time():
    clock = Clock(datetime(2026, 11, 24, 2, 0, tzinfo=TZ))
    fired = []
    sched = Scheduler("0 3 * * *", fired.append, clock)
    assert sched.next_due == datetime(2026, 11, 24, 3, 0, tzinfo=TZ)
    assert not sched.tick(datetime(2026, 11, 24, 2, 59, 59, tzinfo=TZ)) and fired == []
    assert sched.tick(datetime(2026, 11, 24, 3, 0, 5, tzinfo=TZ))
    assert fired == [datetime(2026, 11, 24, 3, 0, tzinfo=TZ)]
    assert not sched.tick(datetime(2026, 11, 24, 3, 0, 40, tzinfo=TZ))  # once, not at every poll
    assert sched.next_due == datetime(2026, 11, 25, 3, 0, tzinfo=TZ)
    # the service was down across two nights: one run when it is back, not one per missed night
    assert sched.tick(datetime(2026, 11, 27, 12, 0, tzinfo=TZ)) and len(fired) == 2
    assert sched.next_due == datetime(2026, 11, 28, 3, 0, tzinfo=TZ)


def test_a_failing_launch_does_not_stop_the_schedule():
    calls = []

    def fire(due):
        calls.append(due)
        raise OSError("fork failed")

    sched = Scheduler("*/15 * * * *", fire, Clock(datetime(2026, 11, 24, 0, 0, tzinfo=TZ)))
    assert sched.tick(datetime(2026, 11, 24, 0, 15, tzinfo=TZ))
    assert sched.tick(datetime(2026, 11, 24, 0, 30, tzinfo=TZ)) and len(calls) == 2


def test_the_thread_fires_on_its_clock_and_stops():
    clock = Clock(datetime(2026, 11, 24, 2, 59, 59, 900000, tzinfo=TZ))
    fired = []
    sched = Scheduler("0 3 * * *", fired.append, clock, poll=0.01)
    sched.start()
    try:
        clock.t = datetime(2026, 11, 24, 3, 0, 1, tzinfo=TZ)
        deadline = datetime.now() + timedelta(seconds=5)
        while not fired and datetime.now() < deadline:
            time.sleep(0.01)
    finally:
        sched.stop()
    assert fired == [datetime(2026, 11, 24, 3, 0, tzinfo=TZ)]


@pytest.mark.parametrize("bad", ["", "0 3 * *", "61 * * * *", "every night", "0 3 * * * * *"])
def test_bad_cron_expressions_are_refused(bad):
    with pytest.raises(ValueError, match="cron"):
        parse_cron(bad)
    if bad.strip():
        with pytest.raises(ValidationError, match="cron"):
            Settings(finetune={"schedule": bad})


def test_the_schedule_can_be_turned_off():
    assert Settings(finetune={"schedule": ""}).finetune.schedule is None
    assert Settings().finetune.schedule == "0 3 * * *"
    with pytest.raises(ValidationError, match="unknown task"):
        Settings(finetune={"eval_tasks": {"lift-cube": ["lift-moon"]}})

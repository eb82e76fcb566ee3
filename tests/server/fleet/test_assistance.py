"""The assistance queue's order: urgency bounded whatever the signal's scale, waiting counts, claimed
requests last, every score and threshold ranked without an exception, and no robot starving. The
clock is passed in (``now``): no sleeps."""

import math

import pytest

from server.fleet.assistance import WAIT_SCALE_S, AskRecord, AssistanceQueue, urgency

LIFT, DRAWER = 0.004, 0.5  # thresholds of two signals on very different scales
LIFT_SCORE, DRAWER_SCORE = 1100 * LIFT, 1.3 * DRAWER  # 1,100x and 1.3x their thresholds


def _open(queue: AssistanceQueue, robot_id: int, score: float, threshold: float, reason: str, now: float):
    return queue.ask(robot_id, AskRecord(None, score, threshold, reason), now)


def _order(queue: AssistanceQueue, now: float) -> list[int]:
    return [r.robot_id for r in queue.pending(now)]


def test_a_robot_that_waited_longer_than_wait_scale_goes_ahead_of_a_fresh_1100x_request():
    q = AssistanceQueue(lease_seconds=30)
    _open(q, 1, DRAWER_SCORE, DRAWER, "spread", now=0.0)
    _open(q, 2, LIFT_SCORE, LIFT, "spread", now=WAIT_SCALE_S + 1)  # fresh, three orders of magnitude over
    assert _order(q, now=WAIT_SCALE_S + 1) == [1, 2]  # by score / threshold it waited ~3 hours for this


def test_a_fresh_high_ratio_request_never_overtakes_a_robot_that_waited_past_wait_scale():
    for opened in (WAIT_SCALE_S + 0.01, 11.0, 30.0, 300.0):  # any time after the drawer waited wait_scale
        q = AssistanceQueue(lease_seconds=30)
        _open(q, 1, DRAWER_SCORE, DRAWER, "spread", now=0.0)
        _open(q, 2, 1e12 * LIFT, LIFT, "spread", now=opened)
        for now in (opened, opened + 1, opened + 100, opened + 1e5):
            assert _order(q, now) == [1, 2], (opened, now)


def test_within_wait_scale_the_urgency_still_ranks_and_one_signal_keeps_its_order():
    q = AssistanceQueue(lease_seconds=30)
    _open(q, 1, DRAWER_SCORE, DRAWER, "spread", now=0.0)
    _open(q, 2, LIFT_SCORE, LIFT, "spread", now=2.0)
    _open(q, 3, 1.5 * LIFT, LIFT, "spread", now=2.0)  # same signal, lower score, same age
    for now in (2.0, 2.0 + 3 * WAIT_SCALE_S):  # 0.999, 0.23 + 0.2 (2 s older), 0.33; plus equal waits
        assert _order(q, now) == [2, 1, 3]


def test_claimed_requests_sort_last_and_the_priority_says_how_far_over_and_how_long():
    q = AssistanceQueue(lease_seconds=30)
    _open(q, 1, LIFT_SCORE, LIFT, "spread", now=0.0)
    _open(q, 2, DRAWER_SCORE, DRAWER, "spread", now=5.0)
    _open(q, 3, 1.0, 1.0, "watchdog: 100 of 200 steps without success", now=5.0)
    assert _order(q, now=5.0) == [1, 2, 3]
    q.claim(1, "op", now=5.0)
    assert _order(q, now=5.0) == [2, 3, 1] and q.waits == [5.0]
    assert q.get(1).priority(10.0) == pytest.approx(1 - 1 / 1100 + 10.0 / WAIT_SCALE_S)
    assert q.get(2).priority(10.0) == pytest.approx(1 - 1 / 1.3 + 5.0 / WAIT_SCALE_S)
    assert q.get(3).priority(10.0) == pytest.approx(5.0 / WAIT_SCALE_S)  # the watchdog's: its wait alone


@pytest.mark.parametrize(
    ("score", "threshold", "expected"),
    [
        (5.0, 0.0, 0.0),  # no scale to measure against: by waiting alone
        (5.0, -1.0, 0.0),  # a signal told to ask at every step
        (-0.5, -1.0, 0.0),
        (-2.0, 1.0, 0.0),  # under its threshold
        (1.0, 1.0, 0.0),  # at it: the watchdog's and an operator's requests
        (math.nan, 1.0, 0.0),
        (math.nan, math.nan, 0.0),
        (3.0, math.nan, 0.0),
        (3.0, math.inf, 0.0),
        (math.inf, 1.0, 1.0),
        (-math.inf, 1.0, 0.0),
        (math.inf, -1.0, 0.0),
        (1e308, 1e-308, 1.0),
        (2.0, 1.0, 0.5),
    ],
)
def test_every_score_and_threshold_give_a_bounded_urgency_and_a_finite_priority(score, threshold, expected):
    assert urgency(score, threshold) == expected
    q = AssistanceQueue(lease_seconds=30)
    _open(q, 1, score, threshold, "odd", now=0.0)
    _open(q, 2, 1.0, 1.0, "watchdog", now=-2 * WAIT_SCALE_S)  # waited longer than any urgency is worth
    assert [math.isfinite(r.priority(3.0)) for r in q.pending(3.0)] == [True, True]
    assert _order(q, now=3.0) == [2, 1]


def test_no_robot_starves_one_operator_serving_three_1100x_robots_and_a_1_3x_one():
    """Three lift robots ask again 1 s after each hand-back; one operator spends 5 s per takeover. The
    drawer robot is served within wait_scale + queue length x takeover (by score / threshold it was
    never served here)."""
    takeover, again, n = 5.0, 1.0, 4
    q = AssistanceQueue(lease_seconds=1e9)
    for robot in range(3):
        _open(q, robot, LIFT_SCORE, LIFT, "spread", now=0.0)
    _open(q, 3, DRAWER_SCORE, DRAWER, "spread", now=0.0)
    asks_at: dict[int, float] = {}
    served = [0] * n
    now = 0.0
    while now < 600.0:
        for robot, t in list(asks_at.items()):
            if t <= now:
                score, threshold = (DRAWER_SCORE, DRAWER) if robot == 3 else (LIFT_SCORE, LIFT)
                _open(q, robot, score, threshold, "spread", now=t)
                del asks_at[robot]
        head = q.pending(now)[0]  # the operator takes the head of the queue
        q.claim(head.robot_id, "op", now=now)
        served[head.robot_id] += 1
        now += takeover
        q.close(head.robot_id)
        asks_at[head.robot_id] = now + again
    still_waiting = [now - r.created for r in q.pending(now)]
    longest = max([*q.waits, *still_waiting])
    assert longest <= WAIT_SCALE_S + n * takeover
    assert served[3] >= 20 and sum(served) == len(q.waits) == 120


def _watchdog(q: AssistanceQueue, robot_id: int, now: float) -> None:
    from policy.controller import WATCHDOG
    from server.fleet.assistance import AskRecord

    q.ask(robot_id, AskRecord(WATCHDOG, 1.0, 1.0, "watchdog: 160 of 200 steps without success"), now=now)


def test_cur_puts_stalled_robots_first_then_urgency_and_lets_an_old_request_wait():
    """Fleet-DAgger's CUR: constraint violations (the watchdog's stalled robots) first, then uncertainty;
    no waiting term, so a low-urgency request that waited 100 wait scales still goes last."""
    q = AssistanceQueue(lease_seconds=30, order="cur")
    _open(q, 1, DRAWER_SCORE, DRAWER, "spread", now=0.0)
    _open(q, 2, LIFT_SCORE, LIFT, "spread", now=50.0)
    _watchdog(q, 3, now=90.0)
    _open(q, 4, 1.5 * LIFT, LIFT, "spread", now=95.0)
    assert _order(q, now=100 * WAIT_SCALE_S) == [3, 2, 4, 1]
    q.claim(3, "op", now=100.0)
    assert _order(q, now=100.0) == [2, 4, 1, 3]  # claimed requests still last


def test_fcfs_serves_the_request_opened_first_whatever_the_scores():
    q = AssistanceQueue(lease_seconds=30, order="fcfs")
    _open(q, 1, 1.5 * LIFT, LIFT, "spread", now=0.0)
    _watchdog(q, 2, now=1.0)
    _open(q, 3, 1e12 * LIFT, LIFT, "spread", now=2.0)
    assert _order(q, now=2.0) == [1, 2, 3]
    q.claim(1, "op", now=3.0)
    assert _order(q, now=3.0) == [2, 3, 1]


def test_an_unknown_order_is_refused_when_the_queue_is_made_and_the_settings_name_every_order():
    import typing

    from server.fleet.assistance import QUEUE_ORDERS
    from server.settings import QueueSettings

    with pytest.raises(ValueError, match="unknown queue order 'lifo'"):
        AssistanceQueue(lease_seconds=30, order="lifo")
    assert typing.get_args(QueueSettings.model_fields["order"].annotation) == QUEUE_ORDERS

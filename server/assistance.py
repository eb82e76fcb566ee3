"""The assistance queue: requests ordered by uncertainty and waiting time; a claim is a lease.

One controller per robot. A claim lasts ``lease_seconds`` and is renewed by heartbeats; when it
expires the request returns to the queue (the robot holds meanwhile). Thread-safe.
"""

from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass, field

from server.errors import ServiceError


@dataclass
class AssistanceRequest:
    id: int
    robot_id: int
    uncertainty: float
    threshold: float
    reason: str
    created: float = field(default_factory=time.monotonic)
    created_wall: float = field(default_factory=time.time)
    holder: str | None = None
    lease_until: float | None = None
    claimed_at: float | None = None
    requeued: int = 0
    expired_holder: str | None = None  # who held the lease that ran out last

    def priority(self, now: float, wait_scale: float = 10.0) -> float:
        """Higher first: U relative to its threshold, plus one unit per ``wait_scale`` seconds waited."""
        rel = self.uncertainty / self.threshold if self.threshold > 0 else self.uncertainty
        return rel + (now - self.created) / wait_scale


class AssistanceQueue:
    def __init__(self, lease_seconds: float) -> None:
        self.lease_seconds = lease_seconds
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._by_robot: dict[int, AssistanceRequest] = {}
        self.waits: list[float] = []  # seconds from request to claim, for metrics

    def open(self, robot_id: int, uncertainty: float, threshold: float, reason: str) -> AssistanceRequest:
        with self._lock:
            if robot_id in self._by_robot:
                return self._by_robot[robot_id]
            req = AssistanceRequest(next(self._ids), robot_id, uncertainty, threshold, reason)
            self._by_robot[robot_id] = req
            return req

    def pending(self) -> list[AssistanceRequest]:
        now = time.monotonic()
        with self._lock:
            return sorted(self._by_robot.values(), key=lambda r: (r.holder is not None, -r.priority(now)))

    def get(self, robot_id: int) -> AssistanceRequest | None:
        with self._lock:
            return self._by_robot.get(robot_id)

    def claim(self, robot_id: int, operator: str) -> AssistanceRequest:
        now = time.monotonic()
        with self._lock:
            req = self._by_robot.get(robot_id)
            if req is None:
                raise ServiceError(
                    409,
                    f"robot {robot_id} has no open assistance request: it is neither waiting for help nor under teleop",
                )
            if req.holder is not None and req.holder != operator and req.lease_until and req.lease_until > now:
                raise ServiceError(409, f"robot {robot_id} is already controlled by another operator")
            if req.holder is None:
                self.waits.append(now - req.created)
            req.holder, req.lease_until, req.claimed_at = operator, now + self.lease_seconds, now
            return req

    def heartbeat(self, robot_id: int, operator: str) -> AssistanceRequest:
        with self._lock:
            req = self._holder_check(robot_id, operator)
            req.lease_until = time.monotonic() + self.lease_seconds
            return req

    def check_holder(self, robot_id: int, operator: str) -> AssistanceRequest:
        with self._lock:
            return self._holder_check(robot_id, operator)

    def _holder_check(self, robot_id: int, operator: str) -> AssistanceRequest:
        req = self._by_robot.get(robot_id)
        if req is None:
            raise ServiceError(
                409, f"robot {robot_id} has no open assistance request: it is neither waiting for help nor under teleop"
            )
        if req.holder != operator:
            raise ServiceError(409, f"robot {robot_id} is not controlled by you: claim it first")
        return req

    def close(self, robot_id: int) -> AssistanceRequest | None:
        with self._lock:
            return self._by_robot.pop(robot_id, None)

    def expire(self) -> list[AssistanceRequest]:
        """Returns claims whose lease ran out, now back in the queue."""
        now = time.monotonic()
        out = []
        with self._lock:
            for req in self._by_robot.values():
                if req.holder is not None and req.lease_until is not None and req.lease_until <= now:
                    req.expired_holder, req.holder, req.lease_until = req.holder, None, None
                    req.requeued += 1
                    out.append(req)
        return out

"""Policy hot swap: which loaded policy version (slot) each lineage the fleet serves is driven by.

Policies swap without a restart. The registry (``server.registry``) says which version of each
lineage is active; ``sync_policies`` (called by a watcher thread every ``policy_poll_seconds``, and at
once by ``activate_policy``) loads a newly active version outside the fleet lock, and each robot of
that lineage moves to it at its next episode boundary (``move_to_assigned``, called by the control
loop when it opens an episode); a robot in the middle of an episode finishes it on the version it
started with. So ``hitl policy promote`` or a fine-tuning job's promotion, from another process,
reaches the running fleet the same way as the admin API.

A collaborator of ``server.fleet.fleet.Fleet``, not a part of it: it owns the loaded slots and the lineage
assignments, and only reads the fleet's robots (under the fleet's lock, which it is given). Loading a
version is slow (weights, a trace), so it happens under its own lock, one load at a time, and only the
assignment takes the fleet lock: a tick never waits for a load.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from sqlalchemy.orm import sessionmaker

from policy.checkpoint import CheckpointError, check_fits, read_info
from server import registry
from server.db import PolicyVersion
from server.errors import ServiceError
from server.fleet.robot import Robot
from server.fleet.slots import PolicySlot, load_slot
from server.settings import Settings
from sim.registry import make_task

log = logging.getLogger("hitl.fleet")


class PolicySwap:
    """The fleet's policy slots and the version each lineage serves. lock: the fleet's lock (it guards
    ``robots``, ``slots`` and ``assigned`` against the control tick); robots: the fleet's robots."""

    def __init__(
        self, settings: Settings, sessions: sessionmaker, lock: threading.RLock, robots: dict[int, Robot]
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.lock = lock
        self.robots = robots
        self.slots: dict[int, PolicySlot] = {}  # by policy version id
        self.assigned: dict[str, PolicySlot] = {}  # lineage -> the slot its robots move to at their next episode
        self._unloadable: dict[int, str] = {}  # active versions that failed to load, and why (not retried)
        self._lineages = registry.LineageCache(sessions)
        self._swap_lock = threading.Lock()  # one policy load at a time (outside the fleet lock)

    def serve(self, path: Path, task: str) -> PolicySlot:
        """The configured policy of a robot group, registered, and its lineage's active version loaded: a
        version promoted since (a fine-tuned one) is served, not the configured folder; a lineage with
        no active version gets the configured folder as its active one."""
        key = str(Path(path).resolve())
        with self.sessions() as s:
            row = registry.by_path(s, key)
        if row is None:
            info = _policy_info(Path(key))
            row = registry.register(
                self.sessions, key, info.get("task", task), status="candidate", command=info.get("command")
            )
        try:
            active = registry.resolve(self.sessions, registry.PolicyRef(row.name))
        except ServiceError:  # no active version yet
            active = registry.promote(self.sessions, row.id, "configured in the service's settings")
        if active.id != row.id:
            log.info(
                "%s is configured, but %s is the active version of its lineage (%s): serving it; "
                "`hitl policy promote %s` serves the configured one",
                key,
                active.ref,
                active.status_reason,
                row.ref,
            )
        if active.id in self._unloadable:
            active = row
        if active.id not in self.slots:
            try:
                slot = load_slot(self.settings, registry.folder(active), task, active.id, active.name)
            except ServiceError as exc:
                if active.id == row.id:
                    raise
                log.error(
                    "the active %s cannot be served (%s): serving the configured %s", active.ref, exc.message, row.ref
                )
                self._unloadable[active.id] = exc.message
                active = row
                slot = self.slots.get(row.id) or load_slot(self.settings, registry.folder(row), task, row.id, row.name)
            self.slots[active.id] = slot
            self.assigned[active.name] = slot
            with self.sessions() as s:
                s.get(PolicyVersion, active.id).threshold = slot.threshold
                s.commit()
        return self.slots[active.id]

    def move_to_assigned(self, robot: Robot) -> None:
        """At an episode boundary (fleet lock held): the robot moves to the version assigned to its
        lineage, if that is another one; a version no robot is left on is freed (its weights and trace)."""
        target = self.assigned.get(robot.slot.lineage)
        if target is not None and target is not robot.slot:
            old = robot.slot
            old.controller.remove(robot.id)
            robot.slot = target
            in_use = [r.slot for r in self.robots.values()] + list(self.assigned.values())
            if all(slot is not old for slot in in_use):
                self.slots.pop(old.version, None)  # no robot left on it: its weights and trace are freed
                old.controller.inference.close()  # and its inference actor, if it has one

    def watch(self, stop: threading.Event) -> None:
        """The registry watcher thread: ``sync_policies`` every ``policy_poll_seconds`` until ``stop``."""
        while not stop.wait(self.settings.policy_poll_seconds):
            try:
                self.sync_policies()
            except Exception:  # noqa: BLE001 - a database hiccup: the next poll tries again
                log.exception("policy registry poll failed")

    def register_policy(self, path: Path, task: str | None = None, parent: int | None = None) -> int:
        """Adds a policy folder as a ``candidate`` version (idempotent by path); returns its id."""
        key = str(Path(path).resolve())
        info = _policy_info(Path(key))
        task = task or info.get("task")
        # the request conflicts with what the folder holds (409), which no schema of the request can say
        if task is None:
            raise ServiceError(409, f"{key}/config.json names no task: give one")
        _task_spec(task)  # 422: no such task
        try:
            check_fits(info, task, key)
        except CheckpointError as exc:
            raise ServiceError(409, str(exc)) from exc
        return registry.register(self.sessions, key, task, parent=parent, command=info.get("command")).id

    def lineages(self, max_age: float = 5.0) -> tuple[registry.LineageSummary, ...]:
        """The registry's lineages with their active version and last fine-tuning job (the console's
        view), read from the database at most every ``max_age`` seconds."""
        return self._lineages.get(max_age)

    def served_lineages(self) -> set[str]:
        with self.lock:
            return {r.slot.lineage for r in self.robots.values()} | set(self.assigned)

    def sync_policies(self) -> list[int]:
        """Loads the registry's active version of every lineage the fleet serves, if it is not the one
        assigned yet; returns the versions newly assigned. A version that cannot be loaded is logged
        once and the fleet keeps its current one."""
        changed = []
        with self._swap_lock:
            active = registry.active_versions(self.sessions)
            for lineage in sorted(self.served_lineages()):
                row = active.get(lineage)
                current = self.assigned.get(lineage)
                if row is None or (current is not None and current.version == row.id) or row.id in self._unloadable:
                    continue
                try:
                    slot = self._load(row)
                except ServiceError as exc:
                    self._unloadable[row.id] = exc.message
                    log.error(
                        "policy %s is active but cannot be served, keeping the current one: %s", row.ref, exc.message
                    )
                    continue
                with self.lock:
                    self.slots[row.id] = slot
                    self.assigned[lineage] = slot
                changed.append(row.id)
                log.info(
                    "policy %s (%s) now serves lineage %s from each robot's next episode", row.ref, row.path, lineage
                )
        return changed

    def _load(self, row: PolicyVersion) -> PolicySlot:
        """The slot of a version (slow: no fleet lock), its threshold recorded; ServiceError 422 when it
        cannot drive every robot of its lineage (``policy.checkpoint.check_fits``: another observation
        layout, action size or a chunking longer than a task's horizon)."""
        with self.lock:
            tasks = {r.task for r in self.robots.values() if r.slot.lineage == row.name}
        info = _policy_info(registry.folder(row)) if tasks else {}
        for task in sorted(tasks):
            _task_spec(task)
            try:
                check_fits(info, task, row.ref)
            except CheckpointError as exc:
                raise ServiceError(422, f"{exc} (its lineage's {task} robots)") from exc
        slot = self.slots.get(row.id) or load_slot(self.settings, registry.folder(row), row.task, row.id, row.name)
        with self.sessions() as s:
            s.get(PolicyVersion, row.id).threshold = slot.threshold
            s.commit()
        return slot

    def activate_policy(self, version: int, reason: str | None = None) -> None:
        """Promotes ``version`` in the registry and, when the fleet serves its lineage, loads it first (a
        version that cannot be served is refused with 422 and the registry is left as it was); each
        robot of the lineage moves to it at its next episode boundary."""
        row = registry.by_id(self.sessions, version)
        if row.name in self.served_lineages():
            with self._swap_lock:
                slot = self._load(row)
                with self.lock:
                    self.slots[row.id] = slot
            self._unloadable.pop(row.id, None)
        registry.promote(self.sessions, version, reason)
        self.sync_policies()


def _policy_info(path: Path) -> dict:
    """The folder's ``config.json``: 404 where there is none (no policy there), 422 where it is broken."""
    if not (path / "config.json").is_file():
        raise ServiceError(404, f"no policy folder at {path}: it has no config.json (hitl train writes one)")
    try:
        return read_info(path)
    except CheckpointError as exc:
        raise ServiceError(422, str(exc)) from exc


def _task_spec(task: str):
    try:
        return make_task(task)
    except KeyError as exc:
        raise ServiceError(422, str(exc)) from exc

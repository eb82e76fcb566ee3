"""``/policies``: the policy registry (list, register, promote, roll back) for viewers and admins.

Promotion and rollback change the registry and hot-swap the running fleet at each robot's next
episode (``Fleet.activate_policy``); ``hitl policy promote | rollback`` from a shell does the same
through the database, and the fleet follows within ``policy_poll_seconds``.
"""

from __future__ import annotations

import errno
from pathlib import Path

from fastapi import APIRouter

from server import registry
from server.api.deps import Admin, FleetDep, SessionsDep, Viewer
from server.api.responses import AUTH, BODY, errors
from server.api.schemas import Id, PolicyIn, PolicyName, PolicyOut, PromoteIn, RollbackIn
from server.errors import ServiceError

router = APIRouter(tags=["policies"])


def _out(fleet, rows) -> list[PolicyOut]:
    """The rows, each with the robots running it and, for those it runs, its asking signal and threshold
    (the row's ``threshold`` is the paper's denoising one: ``paper_threshold``)."""
    running: dict[int, list[int]] = {}
    asking: dict[int, dict] = {}
    for r in fleet.views():
        running.setdefault(r.slot.version, []).append(r.id)
        asking[r.slot.version] = {"asking_signal": r.slot.asking or None, "asking_threshold": r.slot.asking_threshold}
    return [
        PolicyOut.model_validate(row).model_copy(
            update={"robots": running.get(row.id, []), "paper_threshold": row.threshold} | asking.get(row.id, {})
        )
        for row in rows
    ]


@router.get("/policies", response_model=list[PolicyOut], responses=errors(AUTH, 404, 422))
def policies(sessions: SessionsDep, fleet: FleetDep, _: Viewer, name: PolicyName | None = None) -> list:
    """Policy versions (of one lineage with ``name``): status, reason, parent, manifest, calibration,
    evaluation, the command that made each, and the robots running it."""
    return _out(fleet, registry.versions(sessions, name))


@router.post(
    "/policies",
    response_model=PolicyOut,
    status_code=201,
    responses=errors(
        AUTH,
        BODY,
        404,
        409,
        why={
            404: "no policy folder at path, or no policy version parent_id",
            409: "the folder's policy does not fit the task (its observation size), or names no task and none is given",
            422: "the request does not validate, or the folder holds a broken policy",
        },
    ),
)
def register_policy(body: PolicyIn, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Registers a policy folder as a ``candidate``: the next version of its parent's lineage, or of a
    lineage named after the folder (the same folder again: the same version)."""
    try:
        version = fleet.register_policy(Path(body.path), body.task, body.parent_id)
    except OSError as exc:  # the folder cannot be looked at: a name too long (no such folder), no permission
        status = 404 if exc.errno in (errno.ENAMETOOLONG, errno.ENOENT, errno.ENOTDIR) else 422
        raise ServiceError(status, f"policy folder {body.path[:200]!r} cannot be read: {exc.strerror}") from exc
    return _out(fleet, [registry.by_id(sessions, version)])[0]


_SWAP = {
    404: "no such policy or version",
    409: "nothing to roll back to",
    422: "the request does not validate, or the version's folder cannot be loaded",
}


@router.post("/policies/promote", response_model=PolicyOut, responses=errors(AUTH, BODY, 404, why=_SWAP))
def promote(body: PromoteIn, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Makes ``NAME@VERSION`` active and retires the lineage's active version. A lineage the fleet
    serves loads the version first (a version that cannot be served is refused with 422 and nothing
    changes); each of its robots moves at its next episode boundary."""
    ref = registry.PolicyRef.parse(body.ref)
    if ref.version is None:
        raise ServiceError(422, f"promote which version? give NAME@VERSION, e.g. {ref.name}@2")
    row = registry.resolve(sessions, ref)
    fleet.activate_policy(row.id, body.reason or "promoted through the API")
    return _out(fleet, [registry.by_id(sessions, row.id)])[0]


@router.post("/policies/rollback", response_model=PolicyOut, responses=errors(AUTH, BODY, 404, 409, why=_SWAP))
def rollback(body: RollbackIn, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Retires the lineage's active version and makes its parent active again (hot swap as for promote)."""
    active = registry.resolve(sessions, registry.PolicyRef(body.name))
    parent = registry.by_id(sessions, active.parent_id) if active.parent_id is not None else None
    if parent is None or parent.name != active.name:
        raise ServiceError(409, f"policy {active.ref} has no parent version in its lineage to roll back to")
    fleet.activate_policy(active.parent_id, body.reason or f"rollback from {active.ref} through the API")
    return _out(fleet, [registry.by_id(sessions, active.parent_id)])[0]


@router.post("/policies/{version}/activate", response_model=PolicyOut, responses=errors(AUTH, 404, 422, why=_SWAP))
def activate_policy(version: Id, sessions: SessionsDep, fleet: FleetDep, _: Admin) -> PolicyOut:
    """Promotes the version with this id (as ``/policies/promote``)."""
    fleet.activate_policy(version, "activated through the API")
    return _out(fleet, [registry.by_id(sessions, version)])[0]

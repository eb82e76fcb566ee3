"""Health, readiness, fleet metrics and Prometheus ``/metrics``."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Gauge, generate_latest

from server.api.deps import FleetDep, Viewer
from server.api.responses import AUTH, errors
from server.api.schemas import FleetMetrics, HealthOut, ReadyOut

router = APIRouter(tags=["system"])
api = APIRouter(tags=["metrics"])


@router.get("/healthz", response_model=HealthOut)
def healthz() -> dict:
    return {"status": "ok"}


@router.get("/readyz", response_model=ReadyOut, responses={503: {"model": ReadyOut, "description": "not ready yet"}})
def readyz(request: Request, response: Response) -> dict:
    fleet = getattr(request.app.state, "fleet", None)
    ready = fleet is not None and fleet.ticks > 0
    if not ready:
        response.status_code = 503
    return {"ready": ready}


@api.get("/metrics/fleet", response_model=FleetMetrics, responses=errors(AUTH))
def fleet_metrics(fleet: FleetDep, _: Viewer) -> dict:
    return asdict(fleet.metrics())


@router.get(
    "/metrics",
    # a class without a media type: FastAPI then documents 200 only as the text/plain below, and the
    # errors as JSON (with PlainTextResponse it would document ErrorOut as text/plain too)
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text exposition format",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    }
    | errors(AUTH),
)
def prometheus(fleet: FleetDep, _: Viewer) -> Response:
    """Fleet gauges in the Prometheus text format (``Content-Type: text/plain; version=...``)."""
    registry = CollectorRegistry()
    m = fleet.metrics()
    Gauge("hitl_episodes_total", "finished episodes", registry=registry).set(m.episodes)
    Gauge("hitl_success_rate", "successful episodes / episodes", registry=registry).set(m.success_rate or 0)
    Gauge("hitl_control_ticks_total", "control ticks", registry=registry).set(m.ticks)
    modes = Gauge("hitl_robots", "robots by mode", ["mode"], registry=registry)
    for mode, n in m.robots_by_mode.items():
        modes.labels(mode).set(n)
    Gauge("hitl_queue_length", "open assistance requests", registry=registry).set(len(fleet.requests()))
    for name, doc, value in (
        ("hitl_queue_oldest_unclaimed_seconds", "wait of the oldest unclaimed request", m.queue_oldest_unclaimed_s),
        ("hitl_queue_wait_max_seconds", "longest wait from request to claim", m.queue_wait_max_s),
    ):
        Gauge(name, doc, registry=registry).set(value or 0)
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import time

from fastapi import APIRouter, Response, status
from fastapi.responses import PlainTextResponse

from service.api.deps import ServiceDep
from service.api.models import Health, MissingGains, Readiness, StorageStatus
from service.app import Service
from service.fleet.engine import REJECT_REASONS
from service.metrics import Exposition

router = APIRouter(tags=["health"])


def storage_status(service: Service) -> StorageStatus:
    state = service.storage_state()
    since = state.degraded_since
    return StorageStatus(
        state="degraded" if state.degraded else "ok",
        reason=state.reason,
        pending_writes=state.pending,
        failures=state.failures,
        lost_writes=state.lost,
        degraded_for_s=None if since is None else round(time.monotonic() - since, 3),
    )


@router.get(
    "/health",
    response_model=Health,
    summary="the process is up (503 once a background task cannot be kept running)",
    responses={503: {"model": Health, "description": "a background task failed for good: the process is exiting"}},
)
async def health(service: ServiceDep, response: Response) -> Health:
    answer = Health(
        **service.status(),
        status="failed" if service.fatal is not None else "ok",
        storage=storage_status(service),
        tasks=dict(service.down_tasks),
        ingest_heartbeat_age_s=round(service.ingest_heartbeat_age_s(), 3),
        router_connected=service.router_connected(),
    )
    if service.fatal is not None:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    return answer


@router.get(
    "/ready",
    response_model=Readiness,
    summary="every profile has active gains, Zenoh is connected, ingest runs and the database accepts writes",
    responses={
        503: {
            "model": Readiness,
            "description": "not ready, and why in `detail`: the profiles without active gains and why (designing, "
            "or the failed design's reason), Zenoh down or no router (client mode), the ingest loop stalled, a "
            "background task down, or the storage degraded",
        }
    },
)
async def ready(service: ServiceDep, response: Response) -> Readiness:
    missing = {name: MissingGains.model_validate(why) for name, why in service.missing_gains().items()}
    causes = service.not_ready_causes()
    answer = Readiness(
        ready=not causes,
        transport=service.transport_up,
        profiles={name: bank.version for name, bank in service.engine.banks.items()},
        missing_gains=missing,
        failed_profiles=dict(service.failed_profiles),
        storage=storage_status(service),
        tasks=dict(service.down_tasks),
        router_connected=service.router_connected(),
    )
    if not answer.ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
        answer.detail = _not_ready_detail(answer, causes)
    return answer


def _not_ready_detail(answer: Readiness, causes: list[str]) -> str:
    # the gains are explained profile by profile below
    out = [c for c in causes if c != "not every profile has active gains"]
    if not answer.profiles:
        out.append("no profile is configured")
    for name, why in answer.missing_gains.items():
        if why.state == "designing":
            out.append(f"profile {name!r} has no active gains: designing (job {why.job})")
        elif why.state == "failed":
            out.append(f"profile {name!r} has no active gains: its design failed ({why.error}): {why.reason}")
        else:
            out.append(f"profile {name!r} has no active gains: {why.reason or why.state}")
    return "; ".join(out)


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    summary="Prometheus metrics (text format 0.0.4)",
    responses={200: {"content": {"text/plain": {"example": "agv_fe_measurements_received_total 120000\n"}}}},
)
async def metrics(service: ServiceDep) -> PlainTextResponse:
    engine, m, jobs = service.engine, service.metrics, service.jobs
    out = Exposition()
    out.metric(
        "agv_fe_measurements_received_total",
        "counter",
        "measurements taken from Zenoh",
        [({}, engine.stats["received"])],
    )
    out.metric(
        "agv_fe_measurements_accepted_total",
        "counter",
        "measurements that reached an observer",
        [({}, engine.stats["accepted"])],
    )
    out.metric(
        "agv_fe_measurements_rejected_total",
        "counter",
        "measurements rejected or dropped, by reason",
        [({"reason": r}, engine.rejected[r]) for r in REJECT_REASONS],
    )
    out.metric(
        "agv_fe_samples_missing_total", "counter", "samples missing in sequence gaps", [({}, engine.stats["missing"])]
    )
    out.metric(
        "agv_fe_observer_restarts_total",
        "counter",
        "observer re-initialisations after long gaps",
        [({}, engine.stats["restarts"])],
    )
    out.metric("agv_fe_estimates_total", "counter", "estimates computed", [({}, engine.stats["estimates"])])
    out.metric(
        "agv_fe_estimates_published_total",
        "counter",
        "estimates published on Zenoh, each on its vehicle's key",
        [({}, m.estimates_out)],
    )
    out.metric(
        "agv_fe_fleet_estimates_published_total",
        "counter",
        "estimates published on Zenoh in the replica's one-message-per-tick fleet stream",
        [({}, m.fleet_estimates_out)],
    )
    out.metric(
        "agv_fe_estimate_keys_unmatched",
        "gauge",
        "vehicles whose estimate key no subscriber matched at the last check (their estimates are not sent)",
        [({}, m.estimates_unmatched)],
    )
    out.metric(
        "agv_fe_alarm_events_published_total", "counter", "alarm events stored and published", [({}, m.alarms_out)]
    )
    out.metric(
        "agv_fe_vehicles",
        "gauge",
        "registered vehicles by profile",
        [({"profile": name}, int(bank.used.sum())) for name, bank in engine.banks.items()],
    )
    out.metric("agv_fe_alarms_latched", "gauge", "latched alarms", [({}, len(engine.alarms.latched()))])
    out.metric(
        "agv_fe_ingest_last_batch",
        "gauge",
        "measurements drained in the last tick (the queue depth seen by the ingest loop)",
        [({}, m.last_batch)],
    )
    out.metric(
        "agv_fe_ingest_full_batches_total",
        "counter",
        "ticks that hit ingest.max_batch (backlog)",
        [({}, m.full_batches)],
    )
    out.histogram("agv_fe_tick_seconds", "time to drain, validate, step, alarm and publish one tick", m.tick_seconds)
    out.histogram("agv_fe_tick_batch_measurements", "measurements per tick", m.tick_batch)
    out.histogram("agv_fe_synthesis_seconds", "duration of finished synthesis jobs", m.synthesis_seconds)
    out.metric(
        "agv_fe_synthesis_jobs_total",
        "counter",
        "finished synthesis jobs by outcome",
        [({"status": s}, n) for s, n in jobs.finished.items()],
    )
    out.metric(
        "agv_fe_profiles_failed",
        "gauge",
        "stored profiles that could not be loaded at start-up and do not run (GET /profiles says why)",
        [({}, len(service.failed_profiles))],
    )
    storage = service.storage_state()
    out.metric(
        "agv_fe_storage_degraded",
        "gauge",
        "1 while the database refuses writes (locked, full, failing): they are queued and retried",
        [({}, int(storage.degraded))],
    )
    out.metric("agv_fe_storage_writes_pending", "gauge", "writes queued for the database", [({}, storage.pending)])
    out.metric(
        "agv_fe_storage_write_failures_total", "counter", "failed database write attempts", [({}, storage.failures)]
    )
    out.metric(
        "agv_fe_storage_writes_lost_total",
        "counter",
        "database writes given up (queue full, a write that cannot succeed, or pending at shutdown)",
        [({}, storage.lost)],
    )
    out.metric(
        "agv_fe_background_task_failures_total",
        "counter",
        "failures of the supervised background tasks, by task",
        [({"task": name}, n) for name, n in service.task_failures.items()],
    )
    out.metric(
        "agv_fe_ingest_heartbeat_age_seconds",
        "gauge",
        "time since the ingest loop's latest iteration",
        [({}, round(service.ingest_heartbeat_age_s(), 6))],
    )
    router = service.router_connected()
    if router is not None:
        out.metric(
            "agv_fe_zenoh_router_connected", "gauge", "client mode: 1 while connected to a router", [({}, int(router))]
        )
    out.metric(
        "agv_fe_ready",
        "gauge",
        "1 when /ready answers 200: gains, Zenoh, ingest, background tasks and storage are all fine",
        [({}, int(service.ready))],
    )
    return PlainTextResponse(out.text(), media_type="text/plain; version=0.0.4")

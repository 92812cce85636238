"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from fastapi.responses import PlainTextResponse

from service.api.deps import ServiceDep
from service.api.models import Health, MissingGains, Readiness
from service.fleet.engine import REJECT_REASONS
from service.metrics import Exposition

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, summary="the process is up")
async def health(service: ServiceDep) -> Health:
    return Health(**service.status())


@router.get(
    "/ready",
    response_model=Readiness,
    summary="every profile has active gains and Zenoh is connected",
    responses={
        503: {
            "model": Readiness,
            "description": "not ready: the profiles without active gains and why (designing, or the failed "
            "design's reason), or Zenoh is down",
        }
    },
)
async def ready(service: ServiceDep, response: Response) -> Readiness:
    missing = {name: MissingGains.model_validate(why) for name, why in service.missing_gains().items()}
    answer = Readiness(
        ready=service.ready,
        transport=service.transport_up,
        profiles={name: bank.version for name, bank in service.engine.banks.items()},
        missing_gains=missing,
        failed_profiles=dict(service.failed_profiles),
    )
    if not answer.ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
        answer.detail = _not_ready_detail(answer)
    return answer


def _not_ready_detail(answer: Readiness) -> str:
    causes = [] if answer.transport else ["the Zenoh transport is down"]
    if not answer.profiles:
        causes.append("no profile is configured")
    for name, why in answer.missing_gains.items():
        if why.state == "designing":
            causes.append(f"profile {name!r} has no active gains: designing (job {why.job})")
        elif why.state == "failed":
            causes.append(f"profile {name!r} has no active gains: its design failed ({why.error}): {why.reason}")
        else:
            causes.append(f"profile {name!r} has no active gains: {why.reason or why.state}")
    return "; ".join(causes)


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
    out.metric("agv_fe_ready", "gauge", "1 when every profile has active gains", [({}, int(service.ready))])
    return PlainTextResponse(out.text(), media_type="text/plain; version=0.0.4")

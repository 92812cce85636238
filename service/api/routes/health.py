"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, Response, status

from service.api.deps import ServiceDep
from service.api.models import Health, MissingGains, Readiness, Replicas, StorageStatus
from service.app import Service
from service.metrics import CONTENT_TYPE, exposition

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
    "/replicas",
    response_model=Replicas,
    summary="the live service replicas, by their Zenoh liveliness tokens (a dead replica's goes with its session)",
    responses={503: {"description": "the Zenoh transport is not open"}},
)
async def replicas(service: ServiceDep, response: Response) -> Replicas:
    transport = service.transport
    leases = service.lease_state()
    members = None if leases is None else leases.members
    unowned = service.ownership.unowned
    if transport is None:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
        return Replicas(replica=service.replica_id, replicas=[], lease_replicas=members, unowned_buckets=unowned)
    names = await asyncio.to_thread(transport.replicas)
    return Replicas(replica=service.replica_id, replicas=names, lease_replicas=members, unowned_buckets=unowned)


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
    missing = {name: MissingGains.model_validate(why) for name, why in service.policy.missing_gains().items()}
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
    response_class=Response,
    summary="Prometheus metrics (text format 0.0.4)",
    responses={200: {"content": {"text/plain": {"example": "agv_fe_measurements_received_total 120000.0\n"}}}},
)
async def metrics(service: ServiceDep) -> Response:
    # on the event loop, between two ticks: the collector reads the fleet's arrays as one tick left them
    return Response(exposition(service.registry), media_type=CONTENT_TYPE)

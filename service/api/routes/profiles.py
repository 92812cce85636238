"""Profiles, their gains, and resynthesis."""

from __future__ import annotations

from concurrent.futures.process import BrokenProcessPool
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query, Response, status
from pydantic import AfterValidator

from service.api.deps import STORAGE_UNAVAILABLE, Operator, ServiceDep, profile_bank
from service.api.models import (
    CalibrationProposal,
    CalibrationRequest,
    GainsInfo,
    HTTPError,
    ProfileChange,
    ProfileInfo,
)
from service.app import Service
from service.calibration import base_from_profile, run_calibration
from service.fleet import ProfileBank
from service.profile_policy import TooManyProfiles
from service.profiles import PROFILE_NAME_PATTERN, ProfileSpec, check_profile_name

router = APIRouter(prefix="/profiles", tags=["profiles"])

ProfileName = Annotated[
    str, Path(description="profile name", pattern=PROFILE_NAME_PATTERN), AfterValidator(check_profile_name)
]
AUTH: dict[int | str, dict[str, Any]] = {401: {"description": "missing or invalid token"}}


def _info(service: Service, bank: ProfileBank) -> ProfileInfo:
    pending = service.jobs.pending_for(bank.name)
    return ProfileInfo(
        name=bank.name,
        spec=bank.spec,
        active_version=bank.version,
        gain_versions=[v for v, _ in service.db.gain_versions(bank.name)],
        vehicles=int(bank.used.sum()),
        pending_job=None if pending is None else pending.id,
    )


def _failed_info(service: Service, name: str, error: str) -> ProfileInfo:
    held = sum(1 for profile, _ in service.engine.held.values() if profile == name)
    return ProfileInfo(
        name=name,
        state="failed",
        error=error,
        spec=None,
        active_version=None,
        gain_versions=[v for v, _ in service.db.gain_versions(name)],
        vehicles=held,
        pending_job=None,
    )


@router.get("", response_model=list[ProfileInfo], summary="every profile, running or failed to load")
async def list_profiles(service: ServiceDep) -> list[ProfileInfo]:
    running = [_info(service, bank) for bank in service.engine.banks.values()]
    return running + [_failed_info(service, name, error) for name, error in service.failed_profiles.items()]


@router.get("/{name}", response_model=ProfileInfo, responses={404: {"description": "no such profile"}})
async def get_profile(service: ServiceDep, name: ProfileName) -> ProfileInfo:
    error = service.failed_profiles.get(name)
    if error is not None:
        return _failed_info(service, name, error)
    return _info(service, profile_bank(service, name))


@router.put(
    "/{name}",
    response_model=ProfileChange,
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **AUTH,
        200: {"model": ProfileChange, "description": "only thresholds or limits changed: applied"},
        409: {"model": HTTPError, "description": "a new profile beyond the setting max_profiles"},
        **STORAGE_UNAVAILABLE,
    },
    summary="create or change a profile; new parameters, bounds or design options start a synthesis job",
)
async def put_profile(
    service: ServiceDep, name: ProfileName, spec: ProfileSpec, _operator: Operator, response: Response
) -> ProfileChange:
    service.require_storage()
    try:
        job = service.policy.put_profile(name, spec)
    except TooManyProfiles as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from exc
    await service.stored(f"profile {name!r}")
    if job is None:
        response.status_code = status.HTTP_200_OK
        return ProfileChange(profile=name, job=None, applied=True)
    response.headers["Location"] = f"/jobs/{job.id}"
    return ProfileChange(profile=name, job=job.id, applied=False)


@router.post(
    "/{name}/synthesis",
    response_model=ProfileChange,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**AUTH, 404: {"description": "no such profile"}, **STORAGE_UNAVAILABLE},
    summary="design the profile's gains again (for example after a change of the default design)",
)
async def resynthesise(
    service: ServiceDep, name: ProfileName, _operator: Operator, response: Response
) -> ProfileChange:
    profile_bank(service, name)
    service.require_storage()
    job = service.policy.resynthesise(name)
    await service.stored(f"the design job of profile {name!r}")
    response.headers["Location"] = f"/jobs/{job.id}"
    return ProfileChange(profile=name, job=job.id, applied=False)


@router.post(
    "/{name}/calibration",
    response_model=CalibrationProposal,
    responses={
        **AUTH,
        404: {"description": "no such profile, and no base parameters given"},
        422: {"description": "a bad recording, or recordings that cannot identify the vehicle (the reason)"},
        503: {"description": "the calibration worker died"},
    },
    summary="a profile calibrated from healthy recordings: proposed, applied only by a PUT",
)
async def calibrate(
    service: ServiceDep, name: ProfileName, body: CalibrationRequest, _operator: Operator
) -> CalibrationProposal:
    base: dict[str, Any] | None = body.base
    if base is None:
        bank = service.engine.banks.get(name)
        if bank is None:
            raise HTTPException(
                status.HTTP_404_NOT_FOUND,
                detail=f"no profile {name!r} to take the base parameters from: give 'base' with params.mass_kg, "
                "front_axle_distance_m, rear_axle_distance_m and wheel_radius_m",
            )
        base = base_from_profile(bank.spec)
    elif not isinstance(base.get("params"), dict):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, detail="base.params must be an object")
    request = {
        "base": base,
        "recordings": [r.model_dump() for r in body.recordings],
        "false_alarms_per_1000_h": body.false_alarms_per_1000_h,
        "nominal_torque_nm": body.nominal_torque_nm,
        "gust_n": body.gust_n,
        "effectiveness": body.effectiveness,
    }
    try:
        outcome = await service.jobs.run_in_worker(run_calibration, request)
    except BrokenProcessPool as exc:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, detail=f"the calibration worker died: {exc}") from exc
    if not outcome["ok"]:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, detail=f"{outcome['error']}: {outcome['reason']}")
    return CalibrationProposal(
        profile_name=name, profile=ProfileSpec.model_validate(outcome["profile"]), report=outcome["report"]
    )


@router.get(
    "/{name}/gains",
    response_model=GainsInfo,
    responses={404: {"description": "no such profile, or no active gains yet"}},
    summary="the active gains: certificate summary, matrices on request",
)
async def get_gains(
    service: ServiceDep,
    name: ProfileName,
    matrices: Annotated[bool, Query(description="include N, L, M, E, P, R, T")] = False,
    version: Annotated[str | None, Query(description="a stored version instead of the active one")] = None,
) -> GainsInfo:
    bank = profile_bank(service, name)
    wanted = version or bank.version
    if wanted is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"profile {name!r} has no active gains yet")
    if bank.gains is not None and wanted == bank.version:
        doc = bank.gains.to_dict(matrices=matrices)
    else:
        stored = service.db.gains(name, wanted)
        if stored is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"profile {name!r} has no gain version {wanted!r}")
        doc = stored if matrices else {k: v for k, v in stored.items() if k != "matrices"}
    certificate = dict(doc["certificate"])
    if not matrices:
        certificate.pop("lmi_min_eigenvalues", None)
        certificate.pop("P_min_eigenvalues", None)
    return GainsInfo(
        format=doc["format"],
        profile=name,
        version=doc["version"],
        params=doc["params"],
        bounds=doc["bounds"],
        options=doc["options"],
        certificate=certificate,
        matrices=doc.get("matrices") if matrices else None,
    )

"""Synthesis jobs."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status

from service.api.deps import ServiceDep
from service.api.models import JobInfo

router = APIRouter(prefix="/jobs", tags=["jobs"])


@router.get("", response_model=list[JobInfo], summary="recent synthesis jobs, newest first")
async def list_jobs(service: ServiceDep, limit: Annotated[int, Query(ge=1, le=1000)] = 50) -> list[JobInfo]:
    return [JobInfo(**j) for j in service.db.jobs(limit)]


@router.get("/{job_id}", response_model=JobInfo, responses={404: {"description": "no such job"}}, summary="job status")
async def get_job(service: ServiceDep, job_id: str) -> JobInfo:
    job = service.jobs.get(job_id)
    data = job.to_dict() if job is not None else service.db.job(job_id)
    if data is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"no job {job_id!r}")
    return JobInfo(**data)

"""Synthesis jobs: LMI designs run in worker processes, never on the ingest loop.

A job carries a profile's new spec to a ``spawn`` worker (Zenoh sessions do
not survive ``fork``) as plain dicts, gets back ``gains.to_dict()`` or the
reason of the failure, rebuilds the gains with ``ObserverGains.from_dict``
(hash check and re-verification, in a thread) and hands them to the
activation callback. Requests for one profile are serialised and coalesced:
while a job runs, a newer request replaces any queued one, which ends as
``superseded``. A request that needs no design (the profile's active design
with new thresholds) withdraws the profile's pending jobs: the latest
accepted request wins. A failed job leaves the active gains untouched. A worker
ends itself when the service process is gone, so a crash leaves no orphan
solving for nobody.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import threading
import time
import uuid
from collections.abc import Awaitable, Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from service.affinity import background_cpus, set_process_affinity
from service.profiles import ProfileSpec
from synth.gains import ObserverGains

log = logging.getLogger("agv_fe.service.jobs")

JobStatus = Literal["queued", "running", "succeeded", "failed", "superseded", "interrupted"]
JobKind = Literal["initial", "create", "update", "resynthesis"]
FINAL_STATES = frozenset({"succeeded", "failed", "superseded", "interrupted"})
#: How often a worker checks that the service process that started it still exists [s].
PARENT_CHECK_INTERVAL_S = 0.5


def exit_with_parent(parent_pid: int, cpus: frozenset[int] | None = None) -> None:
    """Worker initializer: end this worker once ``parent_pid`` is gone (killed, crashed); run it on ``cpus``
    (None: those it inherited), the CPUs the service leaves to background work (service/affinity.py).

    A worker blocks on its call queue, whose write end it holds itself, so it
    would never see its parent die; an orphan is re-parented, which changes
    ``os.getppid()``.
    """
    if cpus is not None:
        set_process_affinity(cpus)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_INTERVAL_S)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def run_synthesis(params: dict[str, Any], bounds: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """Worker-process entry point: design gains, or say why not. Only plain data crosses the process boundary."""
    from synth.design import synthesize
    from synth.errors import BadParameters, Infeasible, SolverFailed, SynthesisError, VerificationFailed
    from synth.options import DesignOptions
    from synth.params import OperatingBounds, VehicleParams

    started = time.perf_counter()
    try:
        gains = synthesize(
            VehicleParams.model_validate(params),
            OperatingBounds.model_validate(bounds),
            DesignOptions.model_validate(options),
        )
    except Infeasible as exc:
        return {"ok": False, "error": "infeasible", "reason": exc.reason, "duration_s": time.perf_counter() - started}
    except VerificationFailed as exc:
        return {"ok": False, "error": "unverified", "reason": exc.reason, "duration_s": time.perf_counter() - started}
    except BadParameters as exc:
        return {"ok": False, "error": "bad_parameters", "reason": str(exc), "duration_s": time.perf_counter() - started}
    except SolverFailed as exc:
        return {"ok": False, "error": "solver_failed", "reason": str(exc), "duration_s": time.perf_counter() - started}
    except SynthesisError as exc:
        return {
            "ok": False,
            "error": "synthesis_error",
            "reason": str(exc),
            "duration_s": time.perf_counter() - started,
        }
    return {"ok": True, "gains": gains.to_dict(), "duration_s": time.perf_counter() - started}


@dataclass
class Job:
    """One synthesis request and what became of it."""

    id: str
    profile: str
    kind: JobKind
    spec: dict[str, Any]
    status: JobStatus = "queued"
    created_t_ns: int = field(default_factory=time.time_ns)
    started_t_ns: int | None = None
    finished_t_ns: int | None = None
    duration_s: float | None = None
    gain_version: str | None = None
    certificate: dict[str, Any] | None = None
    error: str | None = None
    reason: str | None = None
    superseded_by: str | None = None
    #: the job that an interruption (a restart) made this one resume
    resumes: str | None = None
    #: set while running when a later request withdrew it: its gains are not activated
    withdrawn: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Job:
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})


#: Called with the job, its spec and verified gains; it activates them (storage first, then the fleet).
Activate = Callable[[Job, ProfileSpec, ObserverGains], Awaitable[None]]
#: Called whenever a job changes, to persist it.
Persist = Callable[[Job], None]


class SynthesisJobs:
    """The job queue: one running job and at most one queued job per profile."""

    def __init__(self, workers: int, activate: Activate, persist: Persist, kept: int = 500) -> None:
        self._workers = workers
        #: finished jobs kept in memory; the oldest beyond are forgotten (running and queued ones never)
        self._kept = kept
        self._activate = activate
        self._persist = persist
        self._executor: ProcessPoolExecutor | None = None
        self._jobs: dict[str, Job] = {}
        self._running: dict[str, Job] = {}
        self._queued: dict[str, tuple[Job, ProfileSpec]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self.durations_s: list[float] = []
        self.finished: dict[str, int] = {s: 0 for s in ("succeeded", "failed", "superseded")}

    def _pool(self) -> ProcessPoolExecutor:
        if self._executor is None:
            self._executor = ProcessPoolExecutor(
                self._workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=exit_with_parent,
                initargs=(os.getpid(), background_cpus()),
            )
        return self._executor

    async def run_in_worker(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn(*args)`` in a worker process (plain data in and out) and wait for it: CPU-heavy work
        (a calibration) that must not stall the ingest loop. A worker that dies is replaced at the next call."""
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._pool(), fn, *args)
        except BrokenProcessPool:
            self._executor = None
            raise

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def __len__(self) -> int:
        return len(self._jobs)

    def _forget_oldest(self) -> None:
        """Keep at most ``kept`` finished jobs in memory (the database keeps its own, pruned by the service)."""
        finished = [job_id for job_id, job in self._jobs.items() if job.status in FINAL_STATES]
        for job_id in finished[: max(0, len(finished) - self._kept)]:
            del self._jobs[job_id]

    def pending_for(self, profile: str) -> Job | None:
        """The newest job of ``profile`` that has not finished."""
        if profile in self._queued:
            return self._queued[profile][0]
        return self._running.get(profile)

    def latest_for(self, profile: str) -> Job | None:
        """The newest job of ``profile`` submitted since this process started, finished or not."""
        return next((job for job in reversed(self._jobs.values()) if job.profile == profile), None)

    def busy(self) -> bool:
        return bool(self._running or self._queued)

    def withdraw(self, profile: str, reason: str) -> list[Job]:
        """A later request made the profile's pending designs pointless: the queued one is superseded at once,
        the running one when it ends (its gains are not activated). Returns the jobs withdrawn."""
        withdrawn: list[Job] = []
        queued = self._queued.pop(profile, None)
        if queued is not None:
            old = queued[0]
            old.status, old.reason, old.finished_t_ns = "superseded", reason, time.time_ns()
            self.finished["superseded"] += 1
            self._persist(old)
            withdrawn.append(old)
        running = self._running.get(profile)
        if running is not None:
            running.withdrawn, running.reason = True, reason
            withdrawn.append(running)
        return withdrawn

    def submit(self, profile: str, spec: ProfileSpec, kind: JobKind, resumes: str | None = None) -> Job:
        """Queue a design of ``spec`` for ``profile``; a queued, not yet started job of the profile is superseded."""
        job = Job(id=f"job-{uuid.uuid4().hex[:12]}", profile=profile, kind=kind, spec=spec.stored(), resumes=resumes)
        self._jobs[job.id] = job
        self._forget_oldest()
        previous = self._queued.pop(profile, None)
        if previous is not None:
            old = previous[0]
            old.status, old.superseded_by, old.finished_t_ns = "superseded", job.id, time.time_ns()
            self.finished["superseded"] += 1
            self._persist(old)
        self._persist(job)
        if profile in self._running:
            self._queued[profile] = (job, spec)
        else:
            self._start(job, spec)
        return job

    def _start(self, job: Job, spec: ProfileSpec) -> None:
        self._running[job.profile] = job
        task = asyncio.get_running_loop().create_task(self._run(job, spec), name=f"synthesis {job.id}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _run(self, job: Job, spec: ProfileSpec) -> None:
        job.status, job.started_t_ns = "running", time.time_ns()
        self._persist(job)
        inputs = spec.design_inputs()
        loop = asyncio.get_running_loop()
        try:
            outcome = await loop.run_in_executor(
                self._pool(), run_synthesis, inputs["params"], inputs["bounds"], inputs["options"]
            )
            if outcome["ok"] and job.withdrawn:
                job.status = "superseded"
            elif outcome["ok"]:
                gains = await asyncio.to_thread(ObserverGains.from_dict, outcome["gains"])
                await self._activate(job, spec, gains)
                job.status, job.gain_version = "succeeded", gains.version
                job.certificate = gains.certificate.summary()
            else:
                job.status, job.error, job.reason = "failed", outcome["error"], outcome["reason"]
            job.duration_s = float(outcome["duration_s"])
            self.durations_s.append(job.duration_s)
        except BrokenProcessPool as exc:
            self._executor = None
            job.status, job.error, job.reason = "failed", "worker_crashed", f"the synthesis worker died: {exc}"
        except asyncio.CancelledError:
            job.status, job.error, job.reason = "interrupted", "shutdown", "the service stopped during the design"
            raise
        except Exception as exc:  # a bad gains document or an activation error must not kill the queue
            log.exception("synthesis job %s failed", job.id)
            job.status, job.error, job.reason = "failed", type(exc).__name__, str(exc)
        finally:
            job.finished_t_ns = time.time_ns()
            if job.status in self.finished:
                self.finished[job.status] += 1
            self._persist(job)
            self._running.pop(job.profile, None)
            self._forget_oldest()
            nxt = self._queued.pop(job.profile, None)
            if nxt is not None and job.error != "shutdown":
                self._start(*nxt)

    async def close(self) -> None:
        """Cancel running jobs and stop the workers without waiting for a solve to finish."""
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for job, _ in self._queued.values():
            job.status, job.error, job.reason = "interrupted", "shutdown", "the service stopped before the design ran"
            self._persist(job)
        self._queued.clear()
        if self._executor is not None:
            # a running solve would otherwise keep shutdown waiting for seconds
            for process in list(getattr(self._executor, "_processes", {}).values()):
                process.terminate()
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

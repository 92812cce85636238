"""Profile and job policy: which profiles run, when a design is requested, and what a finished design changes.

:class:`ProfilePolicy` owns the profiles' side of a replica: loading the stored profiles and their active gains at
start-up (resuming the designs a restart interrupted), creating and changing profiles (a change of the design
inputs starts a synthesis job, a change of thresholds or limits applies at once), activating the gains a job
produced, storing and reporting each job, and, with a database shared by several replicas, following the
profile changes the others make and claiming designs so that one replica runs each. Everything runs on the
service's event loop, between two ingest ticks, like the REST handlers that call it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from concurrent.futures import Future
from contextlib import suppress
from functools import partial
from typing import TYPE_CHECKING, Any, Protocol

from pydantic import ValidationError

from service import logs
from service.fleet import FleetEngine, FleetError
from service.jobs import FINAL_STATES, Job, JobKind, SynthesisJobs
from service.metrics import ServiceMetrics
from service.profiles import (
    DEFAULT_PROFILE_NAME,
    PROFILE_NAME_RULE,
    ProfileSpec,
    load_profiles_file,
    valid_profile_name,
)
from service.settings import Settings
from service.storage import Storage, StorageError, StoredProfile
from service.storage_writer import StorageWriter, Write
from synth.gains import ObserverGains
from synth.observer import RuntimeGains

if TYPE_CHECKING:  # psycopg is imported only by a replica that uses PostgreSQL
    from service.shared_config import SharedConfig

log = logging.getLogger("agv_fe.service")


class TooManyProfiles(Exception):
    """A new profile beyond the setting max_profiles (the API answers 409 with this message)."""


class ProfileLoadError(Exception):
    """A stored profile the service cannot run; the text says why. The other profiles run."""


class Database(Protocol):
    """The database as the policy uses it: the service's connection for reads, and its queue of writes."""

    @property
    def db(self) -> Storage: ...

    @property
    def writer(self) -> StorageWriter | None: ...

    def store(self, what: str, apply: Write) -> Future[None]: ...


def _valid_spec(stored: dict[str, Any]) -> ProfileSpec | None:
    """A job's stored spec, or None if it is no longer a valid profile (stored before a validation was added)."""
    try:
        return ProfileSpec.model_validate(stored)
    except ValidationError as exc:
        log.error("an interrupted design's spec is not a valid profile, not resumed: %s", exc)
        return None


class ProfilePolicy:
    """The profiles of one replica, their designs and their jobs.

    Parameters
    ----------
    settings : Settings
        the service's settings (profiles_file, max_profiles, synthesis_workers, jobs_kept)
    engine : FleetEngine
        the fleet whose profiles this policy adds, changes and activates gains for
    database : Database
        reads and queued writes (the running service)
    metrics : ServiceMetrics
        where the synthesis times are counted
    """

    def __init__(self, settings: Settings, engine: FleetEngine, database: Database, metrics: ServiceMetrics) -> None:
        self._settings = settings
        self.engine = engine
        self._database = database
        self._metrics = metrics
        self.jobs = SynthesisJobs(
            settings.synthesis_workers, self._activate_job, self._persist_job, kept=settings.jobs_kept
        )
        #: stored profiles that could not be loaded at start-up, and why; they do not run
        self.failed_profiles: dict[str, str] = {}
        #: with a shared database: profile changes heard from the other replicas, and design claims
        self.shared: SharedConfig | None = None
        self._config_lock = asyncio.Lock()

    # ------------------------------------------------------------------ the shared database

    async def open_shared(self, database_url: str) -> None:
        """Follow the profile changes of the other replicas of the database at ``database_url`` (PostgreSQL)."""
        from service.shared_config import SharedConfig

        loop = asyncio.get_running_loop()
        self.shared = SharedConfig(
            database_url,
            on_change=lambda name: asyncio.run_coroutine_threadsafe(self._config_changed(name), loop),
        )
        await asyncio.to_thread(self.shared.open)

    def start_listening(self) -> None:
        """Hear the other replicas' changes from now on (once the service runs)."""
        if self.shared is not None:
            self.shared.start_listening()

    async def close_shared(self) -> None:
        """Stop following; the claims go with the session: another replica designs what this one leaves unfinished."""
        if self.shared is not None:
            await asyncio.to_thread(self.shared.close)
            self.shared = None

    # ------------------------------------------------------------------ start-up

    async def load(self) -> None:
        """Every stored profile with its active gains; the profiles of settings.profiles_file (or the default
        profile) stored first when the database has none."""
        storage = self._database.db
        stored = storage.profiles()
        if not stored:
            initial = (
                load_profiles_file(self._settings.profiles_file)
                if self._settings.profiles_file is not None
                else {DEFAULT_PROFILE_NAME: ProfileSpec()}
            )
            now = time.time_ns()
            for name, spec in initial.items():
                storage.put_profile(name, spec.stored(), now)
            stored = storage.profiles()
        resume = self._interrupted_designs(storage)
        for profile in stored:
            await self._load_profile(profile, resume.get(profile.name))

    def _interrupted_designs(self, storage: Storage) -> dict[str, Job]:
        """Designs accepted (202) but not finished when the service stopped, marked interrupted: each profile's
        latest, to resume (those another replica of a shared database is running are left to it)."""
        resume: dict[str, Job] = {}
        for interrupted in (j for j in storage.jobs(limit=1000) if j["status"] in ("queued", "running")):
            job = Job.from_dict(interrupted)
            if not self._claim(job.profile):
                continue  # another replica of the shared database is running this design
            job.status, job.error, job.reason = "interrupted", "restart", "the service restarted during the design"
            storage.put_job(job.to_dict())
            if job.profile not in resume or job.created_t_ns > resume[job.profile].created_t_ns:
                resume[job.profile] = job
        return resume

    async def _load_profile(self, profile: StoredProfile, earlier: Job | None) -> None:
        """One stored profile into the fleet with its active gains; its interrupted design resumed (``earlier``),
        or its first design started when it has no gains; a profile that cannot load is reported, not fatal."""
        try:
            spec = self._add_stored_profile(profile)
        except ProfileLoadError as exc:
            # one profile the service cannot run must not keep the others from running
            self.failed_profiles[profile.name] = str(exc)
            log.error("stored profile %r cannot be loaded and does not run: %s", profile.name, exc)
            return
        if profile.active_version:
            await self._activate_stored_gains(profile.name, profile.active_version)
        resumed = None if earlier is None else _valid_spec(earlier.spec)
        if earlier is not None and resumed is not None:
            log.warning("profile %s: resuming the design of job %s, interrupted by a restart", profile.name, earlier.id)
            self.jobs.submit(profile.name, resumed, earlier.kind, resumes=earlier.id)
        elif self.engine.banks[profile.name].gains is None:
            if self._claim(profile.name):
                self.jobs.submit(profile.name, spec, "initial")
            else:
                log.info("profile %s: another replica designs its gains; this one activates them", profile.name)
        self._release_claim(profile.name)  # unless a design of the profile is pending here

    def _add_stored_profile(self, profile: StoredProfile) -> ProfileSpec:
        """Validate a stored profile as a request body would be and add it to the fleet, or say why not."""
        if not valid_profile_name(profile.name):
            raise ProfileLoadError(f"invalid profile name {profile.name!r}: use {PROFILE_NAME_RULE}")
        if profile.problem is not None:
            raise ProfileLoadError(profile.problem)
        try:
            spec = ProfileSpec.model_validate(profile.spec)
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
            raise ProfileLoadError(f"the stored spec is not a valid profile: {problems}") from exc
        try:
            self.engine.add_profile(profile.name, spec)
        except (FleetError, ArithmeticError, ValueError) as exc:
            raise ProfileLoadError(f"the profile cannot run: {type(exc).__name__}: {exc}") from exc
        return spec

    async def _activate_stored_gains(self, name: str, version: str) -> None:
        """The profile's stored active gains, re-verified; unusable ones are logged and the profile resynthesised."""
        try:
            gains_doc = self._database.db.gains(name, version)
            if gains_doc is None:
                raise StorageError(f"gain version {version} of profile {name} is not in the database")
            gains = await asyncio.to_thread(ObserverGains.from_dict, gains_doc)
            runtime = RuntimeGains.from_gains(gains)
        except Exception as exc:
            log.error("stored gains %s of %s are unusable (%s): resynthesising", version, name, exc)
            return
        self.engine.activate(name, gains, runtime)

    # ------------------------------------------------------------------ profiles and jobs

    def put_profile(self, name: str, spec: ProfileSpec) -> Job | None:
        """Create or change a profile. A change of the design inputs starts a job; otherwise it applies at once.

        A new profile is added to the fleet before it is stored: one that cannot run is never stored (a stored
        profile is loaded at every start). A profile that failed to load at start-up is replaced. The writes are
        queued: the API awaits the service's ``stored`` before it answers."""
        bank = self.engine.banks.get(name)
        if bank is None:
            running = len(self.engine.banks) + len(self.failed_profiles.keys() - {name})
            if running >= self._settings.max_profiles:
                raise TooManyProfiles(
                    f"the service runs {running} profiles, its limit (setting max_profiles = "
                    f"{self._settings.max_profiles}): change an existing profile, or raise the limit"
                )
            self.engine.add_profile(name, spec)
            self._store_profile(name, spec)
            if self.failed_profiles.pop(name, None) is not None:
                log.info("profile %s, which failed to load at start-up, replaced", name)
                self.engine.release_held(name)
            return self.jobs.submit(name, spec, "create")
        if bank.gains is not None and _same_design(bank.gains, spec):
            # the latest request wins: a design still pending for the profile would overwrite this spec
            for job in self.jobs.withdraw(name, "a later request kept the active design and changed only thresholds"):
                log.info("profile %s: job %s withdrawn by a later request", name, job.id)
            self._store_profile(name, spec)
            self.engine.update_profile_spec(name, spec)
            return None
        return self.jobs.submit(name, spec, "update")

    # ------------------------------------------------------------------ one configuration for every replica

    def _claim(self, profile: str) -> bool:
        """Claim the design of ``profile`` for this replica (always granted without a shared database)."""
        return self.shared is None or self.shared.claim(profile)

    def _release_claim(self, profile: str) -> None:
        if self.shared is not None and self.jobs.pending_for(profile) is None:
            self.shared.release(profile)

    async def _config_changed(self, name: str | None) -> None:
        """Another replica changed profile ``name`` (None: any may have changed): follow the shared database.
        One change at a time: a resync that comes while gains are being verified waits for them."""
        async with self._config_lock:
            for stored in self._database.db.profiles():
                if name is None or stored.name == name:
                    await self._follow_stored_profile(stored)
            if name is None:
                self._design_unclaimed()

    async def _follow_stored_profile(self, stored: StoredProfile) -> None:
        """Run the profile as stored: the same active gain version (verified here again), then the same spec."""
        bank = self.engine.banks.get(stored.name)
        if bank is None:
            if stored.name in self.failed_profiles:
                return
            try:
                self._add_stored_profile(stored)
            except ProfileLoadError as exc:
                self.failed_profiles[stored.name] = str(exc)
                log.error("profile %r from the shared database cannot be loaded and does not run: %s", stored.name, exc)
                return
            self.engine.release_held(stored.name)
            log.info("profile %s: created through another replica", stored.name)
        elif self.jobs.pending_for(stored.name) is not None:
            return  # a design of the profile runs here: it activates its own gains (the latest request wins)
        bank = self.engine.banks[stored.name]
        if stored.active_version and stored.active_version != bank.version:
            await self._activate_stored_gains(stored.name, stored.active_version)
            if bank.version != stored.active_version:
                return  # unusable (logged): the spec stays with the gains that run
            log.info("profile %s: gains %s activated through another replica", stored.name, bank.version)
        spec = _valid_spec(stored.spec)
        if spec is not None and spec != bank.spec:
            self.engine.update_profile_spec(stored.name, spec)
            log.info("profile %s: spec changed through another replica", stored.name)

    def _design_unclaimed(self) -> None:
        """Profiles still without gains whose design nobody runs (its replica died): design them here."""
        for name, bank in self.engine.banks.items():
            if bank.gains is None and self.jobs.pending_for(name) is None and self._claim(name):
                log.warning("profile %s: no replica designs its gains; designing them here", name)
                self.jobs.submit(name, bank.spec, "initial")

    def _store_profile(self, name: str, spec: ProfileSpec) -> None:
        self._database.store(
            f"profile {name}", partial(Storage.put_profile, name=name, spec=spec.stored(), t_ns=time.time_ns())
        )

    def resynthesise(self, name: str, kind: JobKind = "resynthesis") -> Job:
        """Design the gains of profile ``name`` again from its spec (raises UnknownProfile)."""
        bank = self.engine.bank(name)
        return self.jobs.submit(name, bank.spec, kind)

    async def _activate_job(self, job: Job, spec: ProfileSpec, gains: ObserverGains) -> None:
        runtime = await asyncio.to_thread(RuntimeGains.from_gains, gains)
        # persist first: what is active is always in the database (waits, off the loop, while the database fails)
        write = partial(
            Storage.activate_gains, name=job.profile, spec=spec.stored(), gains=gains.to_dict(), t_ns=time.time_ns()
        )
        await asyncio.wrap_future(self._database.store(f"gains {gains.version} of profile {job.profile}", write))
        self.engine.update_profile_spec(job.profile, spec)
        self.engine.activate(job.profile, gains, runtime)
        log.info("profile %s: gains %s active (job %s)", job.profile, gains.version, job.id)

    def _persist_job(self, job: Job) -> None:
        """Store a job at each change of state; time and report how it ended."""
        if job.status in FINAL_STATES and self.shared is not None:
            with suppress(RuntimeError):  # after the loop: the claims session ends with the service anyway
                asyncio.get_running_loop().call_soon(self._release_claim, job.profile)
        writer = self._database.writer
        if writer is not None:
            writer.submit(f"job {job.id} ({job.status})", partial(Storage.put_job, record=job.to_dict()))
            if job.status in FINAL_STATES:  # the newest jobs_kept stay in the database
                writer.submit("pruning old jobs", partial(Storage.prune_jobs, keep=self._settings.jobs_kept))
        if job.status in ("succeeded", "failed") and job.duration_s is not None:
            self._metrics.synthesis_seconds.observe(job.duration_s)
        if job.status in FINAL_STATES:
            logs.event(
                "job",
                logging.WARNING if job.status == "failed" else logging.INFO,
                status=job.status,
                id=job.id,
                profile=job.profile,
                kind=job.kind,
                duration_s=None if job.duration_s is None else round(job.duration_s, 3),
                gain_version=job.gain_version,
                error=job.error,
                reason=job.reason,
                superseded_by=job.superseded_by,
            )
        if job.status != "failed":
            return
        bank = self.engine.banks.get(job.profile)
        if bank is not None and bank.version is not None:
            log.warning(
                "profile %s: design job %s failed (%s): %s; gains %s stay active",
                job.profile,
                job.id,
                job.error,
                job.reason,
                bank.version,
            )
        else:
            log.error(
                "profile %s has no active gains: design job %s failed (%s): %s; /ready answers 503 until a design "
                "of the profile succeeds (PUT /profiles/%s)",
                job.profile,
                job.id,
                job.error,
                job.reason,
                job.profile,
            )

    def missing_gains(self) -> dict[str, dict[str, str | None]]:
        """Every profile without active gains, and why: its job is designing, or failed (with the reason)."""
        out: dict[str, dict[str, str | None]] = {}
        for name, bank in self.engine.banks.items():
            if bank.ready:
                continue
            job = self.jobs.pending_for(name)
            if job is not None and job.status not in FINAL_STATES:
                out[name] = {"state": "designing", "job": job.id, "error": None, "reason": "designing"}
                continue
            job = self.jobs.latest_for(name)
            if job is None:
                reason = f"no design requested: PUT /profiles/{name} or POST /profiles/{name}/synthesis"
                out[name] = {"state": "no_job", "job": None, "error": None, "reason": reason}
            else:
                out[name] = {"state": job.status, "job": job.id, "error": job.error, "reason": job.reason}
        return out


def _same_design(gains: ObserverGains, spec: ProfileSpec) -> bool:
    inputs = spec.design_inputs()
    return (
        gains.params.model_dump(mode="json") == inputs["params"]
        and gains.bounds.model_dump(mode="json") == inputs["bounds"]
        and gains.options.model_dump(mode="json") == inputs["options"]
    )

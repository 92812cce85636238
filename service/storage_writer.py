"""The storage writer: every database write of the running service, in order, on a thread of its own.

The event loop queues a write (a vehicle registration, alarm changes, a job
record, a profile or gain activation) and goes on at once; the writer thread
applies the writes one by one on its own connection. A write that fails
because the database is locked, full, unreachable or cannot be written (the
storage's ``transient_errors``: ``sqlite3.OperationalError`` or a lost
PostgreSQL connection, ``OSError``) stays at the head of the queue and is
retried with exponential backoff, so the writes land in the order they were made once the database
recovers. Until then the writer is *degraded* and says why; the queue is
bounded (a write beyond it is lost, counted and logged).

A write that fails for any other reason (a constraint, a corrupt file) would
fail again: it is dropped, counted as lost and logged, and the queue goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

from service.settings import StorageSettings
from service.storage import Storage, StorageUnavailable

log = logging.getLogger("agv_fe.service.storage")

Write = Callable[[Storage], None]


__all__ = ["StorageState", "StorageUnavailable", "StorageWriter", "Write"]


@dataclass(frozen=True)
class StorageState:
    """What the writer reports to /ready, /health and /metrics."""

    degraded: bool
    #: why the last write failed, while degraded
    reason: str | None
    pending: int
    failures: int
    lost: int
    #: time.monotonic() when the current degradation began, None when healthy
    degraded_since: float | None


@dataclass
class _Pending:
    what: str
    apply: Write
    done: Future[None]


class StorageWriter:
    """Writes queued by the event loop, applied in order on one thread, retried while the database fails."""

    def __init__(self, storage: Storage, settings: StorageSettings) -> None:
        """``storage``: a connection of the writer's own (a lock wait or a failing fsync blocks this thread only)."""
        self.settings = settings
        self._storage = storage
        self._queue: deque[_Pending] = deque()
        self._cond = threading.Condition()
        self._closing = False
        self._deadline = float("inf")
        self._reason: str | None = None
        self._degraded_since: float | None = None
        self.failures = 0
        self.lost = 0
        self._thread = threading.Thread(target=self._run, name="storage-writer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the event loop's side

    def submit(self, what: str, apply: Write) -> Future[None]:
        """Queue a write; the future completes once it is committed (or fails if it is lost)."""
        done: Future[None] = Future()
        with self._cond:
            if self._closing:
                self._lose(done, what, "the storage writer is stopped")
                return done
            if len(self._queue) >= self.settings.max_pending_writes:
                self._lose(
                    done, what, f"{len(self._queue)} writes already wait for the database (storage.max_pending_writes)"
                )
                return done
            self._queue.append(_Pending(what, apply, done))
            self._cond.notify()
        return done

    def barrier(self) -> Future[None]:
        """A future that completes once every write queued before it is committed."""
        return self.submit("barrier", lambda _storage: None)

    @property
    def state(self) -> StorageState:
        with self._cond:
            return StorageState(
                degraded=self._reason is not None,
                reason=self._reason,
                pending=len(self._queue),
                failures=self.failures,
                lost=self.lost,
                degraded_since=self._degraded_since,
            )

    def close(self) -> int:
        """Retry the pending writes for up to ``shutdown_flush_s``, then stop; returns how many were lost."""
        with self._cond:
            self._closing = True
            self._deadline = time.monotonic() + self.settings.shutdown_flush_s
            self._cond.notify_all()
        # one attempt may be waiting for a lock when the deadline passes
        self._thread.join(self.settings.shutdown_flush_s + self.settings.busy_timeout_s + 5.0)
        with self._cond:
            left = list(self._queue)
            self._queue.clear()
            for pending in left:
                self._lose(pending.done, pending.what, "the service stopped before the database accepted it")
        if left:
            log.error("the service stopped with %d writes the database did not accept: they are lost", len(left))
        if not self._thread.is_alive():
            self._storage.close()
        return len(left)

    # ------------------------------------------------------------------ the writer thread

    def _run(self) -> None:
        backoff = self.settings.retry_initial_s
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue or time.monotonic() > self._deadline:
                    return
                head = self._queue[0]
            try:
                head.apply(self._storage)
            except self._storage.transient_errors as exc:
                self._failed(head, exc)
                with self._cond:
                    wait = min(backoff, max(0.0, self._deadline - time.monotonic()))
                    self._cond.wait_for(lambda: self._closing and time.monotonic() > self._deadline, timeout=wait)
                backoff = min(2 * backoff, self.settings.retry_max_s)
                continue
            except Exception as exc:  # a write that cannot succeed: drop it, or it would block every later one
                log.exception("storage: %s failed and is dropped", head.what)
                with self._cond:
                    self._queue.popleft()
                    self.failures += 1
                    self._lose(head.done, head.what, f"{type(exc).__name__}: {exc}")
                continue
            backoff = self.settings.retry_initial_s
            with self._cond:
                self._queue.popleft()
                recovered = self._reason is not None
                self._reason, self._degraded_since = None, None
            if recovered:
                log.warning("storage recovered: %d queued writes left to store", len(self._queue))
            if not head.done.done():
                head.done.set_result(None)

    def _failed(self, head: _Pending, exc: BaseException) -> None:
        reason = f"{head.what} failed: {type(exc).__name__}: {exc}"
        with self._cond:
            self.failures += 1
            first = self._reason is None
            self._reason = reason
            if first:
                self._degraded_since = time.monotonic()
            pending = len(self._queue)
        if first:
            log.error("storage degraded: %s; %d writes queued, retried with backoff", reason, pending)

    def _lose(self, done: Future[None], what: str, why: str) -> None:
        if what != "barrier":  # a barrier writes nothing
            self.lost += 1
            log.error("storage: %s is lost: %s", what, why)
        if not done.done():
            done.set_exception(StorageUnavailable(f"{what} was not stored: {why}"))

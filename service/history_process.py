"""The estimate history kept by a process of its own (setting ``history.writer = 'process'``), fed by the
replica's fleet stream.

In the service (:class:`~service.history.EstimateHistory` on a thread, ``history.writer = 'thread'``) the
history's work shares the interpreter, its lock and its garbage collector with the ingest loop: every tick's
batches are held until the writer converts them (so they outlive the young generations and make the full
collections, which hold the lock, more frequent), and once a chunk the sort and the write take a core for a
second or more. In a process of its own the same :class:`EstimateHistory` runs on the fleet stream's messages
(service/fleet_child.py): the service only publishes that stream, which it encodes for any subscriber
anyway, and its interpreter keeps nothing of the history.

Reads (``GET /vehicles/{id}/estimates?start=&end=``) go to the child over a pipe, one at a time, and come back
as an Arrow IPC stream: the files and the estimates not yet written, as in the service. The child's counters
reach /metrics through shared memory. An estimate published in the last milliseconds before the service stops
may not reach the child before it writes its last chunk.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing
import threading
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import pyarrow as pa

from agv_protocol.wire import EstimateBatch
from service.affinity import background_cpus, set_process_affinity
from service.fleet_child import POLL_S, FleetStreamChild, child_session, fleet_key, serve_fleet_stream
from service.history import EstimateHistory, HistoryStats
from service.settings import HistorySettings, ZenohSettings

log = logging.getLogger("agv_fe.service.history_process")

#: The shared counters, in order: HistoryStats' integers, then the fleet messages the child could not read.
_STATS = ("rows_written", "files_written", "files_deleted", "write_failures", "rows_lost", "bytes_on_disk")
_COUNTERS = (*_STATS, "unreadable")
#: How long a read waits for the child's answer [s].
READ_TIMEOUT_S = 30.0


class HistoryUnavailable(RuntimeError):
    """The history process cannot answer (it exited, or did not answer in time)."""


def history_main(
    zenoh_settings: dict[str, Any],
    replica_id: str,
    child_dir: str | None,
    options: dict[str, Any],
    conn: Connection,
    counters: Any,
) -> None:
    """The child: a client session of the service's router (fleet_child.child_session), the fleet stream into an
    EstimateHistory, reads answered from the pipe."""
    settings, session = child_session(zenoh_settings, child_dir)
    history = EstimateHistory(Path(options.pop("directory")), replica_id, **options)
    history.start()
    unreadable = [0]

    def publish_counters(unread: int) -> None:
        unreadable[0] = unread
        stats = history.stats
        counters[: len(_COUNTERS)] = [*(int(getattr(stats, name)) for name in _STATS), unread]

    def every_poll(unread: int) -> None:
        if conn.poll(POLL_S):
            _answer(history, conn)
        publish_counters(unread)

    try:
        serve_fleet_stream(session, fleet_key(replica_id, settings), counters, history.append, every_poll)
    finally:
        history.close()  # what is held is written now
        publish_counters(unreadable[0])
        session.close()  # type: ignore[no-untyped-call]


def _answer(history: EstimateHistory, conn: Connection) -> None:
    """Answer one read request ``(id, vehicle, start_ns, end_ns, limit)`` with ``(id, ipc bytes | error text)``."""
    request_id, vehicle_id, start_ns, end_ns, limit = conn.recv()
    try:
        table = history.read(vehicle_id, start_ns, end_ns, limit)
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as writer:
            writer.write_table(table)
        answer: bytes | str = sink.getvalue().to_pybytes()
    except (OSError, pa.ArrowException, ValueError) as exc:
        answer = f"the history could not be read: {exc}"
    conn.send((request_id, answer))


class HistoryProcess(FleetStreamChild):
    """The service's side of the child: start, :meth:`read`, :attr:`stats`, close (as EstimateHistory has them).

    :meth:`append` does nothing: the tick's estimates reach the child in the fleet stream."""

    def __init__(
        self, zenoh: ZenohSettings, history: HistorySettings, directory: Path, replica_id: str, child_dir: str | None
    ) -> None:
        """``child_dir``: where the child connects (fleet_child.child_session)."""
        self._conn, child_end = _pipe()
        options = {
            "directory": str(directory),
            "retention_s": history.retention_h * 3600.0,
            "chunk_s": history.chunk_s,
            "precision": history.precision,
        }
        super().__init__(
            history_main,
            (zenoh.model_dump(mode="json"), replica_id, child_dir, options, child_end),
            len(_COUNTERS),
            "history",
        )
        self._lock = threading.Lock()
        self._ids = itertools.count()

    def start(self) -> None:
        """Start the child and wait until it subscribes; raise TransportError if it cannot. With the service on
        CPUs of its own (setting ``cpus``), the child runs on the others: no estimate waits for it."""
        self.start_child()
        background = background_cpus()
        if background is not None and self.pid is not None:
            set_process_affinity(background, self.pid)

    def append(self, batches: list[EstimateBatch]) -> None:
        """Nothing to do: the child takes the tick from the fleet stream."""

    @property
    def stats(self) -> HistoryStats:
        stats = HistoryStats()
        for k, name in enumerate(_STATS):
            setattr(stats, name, int(self.shared[k]))
        return stats

    @property
    def unreadable(self) -> int:
        """Fleet-stream messages the child could not read."""
        return int(self.shared[_COUNTERS.index("unreadable")])

    def read(self, vehicle_id: str, start_ns: int, end_ns: int, limit: int | None = None) -> pa.Table:
        """The vehicle's estimates with start_ns <= t_ns < end_ns, oldest first, from the child; raise
        :class:`HistoryUnavailable` if it cannot answer within :data:`READ_TIMEOUT_S`."""
        with self._lock:
            if not self.alive:
                raise HistoryUnavailable("the estimate history process has exited")
            request_id = next(self._ids)
            try:
                self._conn.send((request_id, vehicle_id, start_ns, end_ns, limit))
                answer = self._receive(request_id)
            except (OSError, EOFError) as exc:
                raise HistoryUnavailable(f"the estimate history process did not answer: {exc}") from exc
        if isinstance(answer, str):
            raise HistoryUnavailable(answer)
        return pa.ipc.open_stream(answer).read_all()

    def _receive(self, request_id: int) -> bytes | str:
        """The answer to ``request_id`` (an earlier request's late answer is dropped)."""
        while self._conn.poll(READ_TIMEOUT_S):
            answered, answer = self._conn.recv()
            if answered == request_id:
                return answer
        raise HistoryUnavailable(f"the estimate history process did not answer within {READ_TIMEOUT_S:g} s")

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop the child: it writes the estimates it holds (a large chunk takes seconds), then exits."""
        super().close(timeout_s)
        self._conn.close()


def _pipe() -> tuple[Connection, Connection]:
    """A duplex pipe of the spawn context (the service's end, the child's end)."""
    return multiprocessing.get_context("spawn").Pipe(duplex=True)

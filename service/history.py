"""Every estimate the service publishes, kept on disk for a retention time as Parquet files, and read back.

The ingest loop hands each tick's :class:`~agv_protocol.wire.EstimateBatch` list to :meth:`EstimateHistory.append`
(one queue put); a writer thread gathers them and writes one Parquet file per ``chunk_s`` of service time,
``DIR/YYYY-MM-DD/<start_ns>-<replica>.parquet``, rows sorted by vehicle and time, so that a query for one
vehicle reads only the row groups that hold it. The columns are the estimate record's
(agv_protocol.wire.Estimate): the float channels as float64 (the published values exactly; 33 bytes per
estimate, 12 MB per vehicle-hour at 100 Hz) or float32 (setting history.precision: 15 bytes, 5.6 MB), with
byte-stream-split encoding and zstd (docs/operations.md), the rest as they are (:data:`_ENCODINGS`). Files
older than the retention are deleted by the writer. A write that fails (disk full, directory gone) is counted,
logged and its rows dropped; ingest never waits for the disk.

A chunk's file is written in rounds once its interval is over (:meth:`EstimateHistory._rounds`): each column
made contiguous, the rows' order, then a row group per round, the writer resting between rounds
(:data:`WRITE_REST`) and taking the next ticks meanwhile; written at once, a minute of 1,000 vehicles was a
burst of 3-4 s of a core that made every process on a small machine wait (docs/capacity.md). Until the file is
complete its rows are read from memory.

The writer turns the batches it gathers into an Arrow table every ``CONVERT_S`` and lets the batches go: a
minute of a large fleet's batches kept as Python objects (60,000 batches of lists at 1,000 vehicles) made each
of the collector's full passes over the heap take about 200 ms with the GIL held, a stall of the ingest loop
(docs/benchmarks/service_config.md); Arrow's buffers are not objects the collector visits.

:meth:`EstimateHistory.read` answers one vehicle's estimates in a time range from the files and from the rows
not yet written, as one Arrow table, oldest first.
"""

from __future__ import annotations

import collections
import itertools
import logging
import os
import re
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from agv_protocol.wire import ESTIMATE_COLUMNS, LEVELS, Estimate, EstimateBatch, EstimateRow

log = logging.getLogger("agv_fe.service.history")

#: The Arrow schema of a history file: the estimate record's fields (agv_protocol.wire.Estimate) but ``v`` and ``rev``
#: (a file's columns say which revision's fields it holds).
_FLOAT_COLUMNS = ESTIMATE_COLUMNS
_TYPES: dict[str, pa.DataType] = {
    "vehicle": pa.dictionary(pa.int32(), pa.string()),
    "seq": pa.int64(),
    "t_ns": pa.int64(),
    "in_domain": pa.bool_(),
    "gain_version": pa.dictionary(pa.int32(), pa.string()),
    "level": pa.dictionary(pa.int8(), pa.string()),
    "gain_set": pa.dictionary(pa.int8(), pa.string()),
} | {name: pa.float64() for name in _FLOAT_COLUMNS}
SCHEMA = pa.schema([pa.field(name, _TYPES[name]) for name in Estimate.model_fields if name not in ("v", "rev")])
_FLOAT32_SCHEMA = pa.schema([pa.field(f.name, pa.float32()) if f.name in _FLOAT_COLUMNS else f for f in SCHEMA])
_FILE_NAME = re.compile(r"^(\d{19})-([A-Za-z0-9_.-]+)\.parquet$")
#: Rows per row group: small enough that a vehicle's rows are a few groups of a large fleet's file.
ROW_GROUP_ROWS = 65_536
_GAIN_SETS = pa.array(["fast", "quiet"])
_LEVELS = pa.array(LEVELS)
#: How the columns are written: a dictionary only for the dictionary columns (vehicle, level, gain version and
#: set), byte-stream split for the float channels, deltas for seq and t_ns (sorted by vehicle and time, they
#: step by 1 and by the period), then zstd. Parquet's default tries a dictionary on every column first: on the
#: floats and times it fails, and it cost a minute of 1,000 vehicles' Parquet write 1.8 s of CPU against 0.7 s,
#: for a file 1.5 times as large (6 million rows, docs/capacity.md).
_ENCODINGS: dict[str, Any] = {
    "compression": "zstd",
    "use_dictionary": [name for name in SCHEMA.names if pa.types.is_dictionary(SCHEMA.field(name).type)],
    "column_encoding": {name: "BYTE_STREAM_SPLIT" for name in _FLOAT_COLUMNS}
    | {"seq": "DELTA_BINARY_PACKED", "t_ns": "DELTA_BINARY_PACKED"},
}
#: The writer converts the batches it holds into an Arrow table at least this often [s] (module docstring). The
#: part of a conversion that reads Python objects (the vehicle ids, Python strings) holds the interpreter lock:
#: every 0.25 s, 37,500 rows at 1,500 vehicles, a conversion took 2.8 ms, long enough to show in the ingest loop's
#: p99; every 0.05 s 0.7 ms, and 0.4 ms since the levels come as codes (numpy) instead of names.
CONVERT_S = 0.05
#: How much lower the writer thread's CPU priority is than the service's (a nice increment, :func:`_lower_priority`).
WRITER_NICE = 10
#: A chunk's file is written in rounds, the writer resting this many times as long as each round took before the
#: next (:meth:`EstimateHistory._rounds`): a minute of 1,000 vehicles, 3-4 s of a core at once, becomes rounds of
#: at most 0.5 s spread at a quarter of a core, while the writer goes on taking the ticks.
WRITE_REST = 3.0
#: The longest rest between two rounds of a chunk's write [s].
WRITE_REST_MAX_S = 0.25
#: Once a chunk's columns are contiguous, its parts (a conversion's table each, 1,200 a minute) are released this
#: many per round: freeing a minute's parts of 1,000 vehicles at once held the interpreter lock for 35 ms (a thread
#: due every millisecond was that late), and every thread of the service waited; a hundred hold it about 3 ms.
PARTS_FREED_PER_ROUND = 100


@dataclass
class HistoryStats:
    """What the writer did, for /metrics and /ready."""

    rows_written: int = 0
    files_written: int = 0
    files_deleted: int = 0
    write_failures: int = 0
    rows_lost: int = 0
    last_error: str | None = None
    bytes_on_disk: int = 0


@dataclass
class _Chunk:
    """The estimates of one interval of service time, waiting to be written: the batches of the last
    CONVERT_S, and the tables the earlier ones were converted into."""

    start_ns: int
    batches: list[EstimateBatch] = field(default_factory=list)
    tables: list[pa.Table] = field(default_factory=list)
    rows: int = 0
    converted_ns: int = 0

    def convert(self, now_ns: int) -> None:
        """The batches into one more table (the writer thread, under the history's lock)."""
        if self.batches:
            self.tables.append(batch_table(self.batches))
            self.batches = []
        self.converted_ns = now_ns

    def table(self) -> pa.Table:
        """Every estimate of the chunk as one table of :data:`SCHEMA`, dictionaries unified."""
        parts = [*self.tables, batch_table(self.batches)] if self.batches else self.tables
        return pa.concat_tables(parts).unify_dictionaries() if parts else SCHEMA.empty_table()


@dataclass
class _Write:
    """A chunk on its way to its file: the rounds that write it (:meth:`EstimateHistory._rounds`), one step each."""

    chunk: _Chunk
    path: Path
    rounds: Iterator[None]


def batch_table(batches: Sequence[EstimateBatch]) -> pa.Table:
    """The batches as one table of :data:`SCHEMA` (a column a batch lacks, such as alpha, is null there).

    The batches are grouped by their float columns, gain version and gain-set column (a profile's are all
    alike), and each group becomes a part with one Arrow conversion per column: the per-batch Python work is
    a list append, so that a writer converting a second of a large fleet's batches (about 1,000 at 1,000
    vehicles) holds the GIL for milliseconds, not the tens a loop of numpy calls per batch took. The rows come
    grouped, in batch order within a group: the file is sorted by vehicle and time, a read by time."""
    groups: dict[tuple[tuple[str, ...], str, bool], list[EstimateBatch]] = {}
    for b in batches:
        if len(b):
            groups.setdefault((b.columns, b.gain_version, b.fast is not None), []).append(b)
    if not groups:
        return SCHEMA.empty_table()
    parts = [_group_table(group, columns, version, has_set) for (columns, version, has_set), group in groups.items()]
    return pa.concat_tables(parts).unify_dictionaries() if len(parts) > 1 else parts[0]


def _group_table(group: list[EstimateBatch], columns: tuple[str, ...], version: str, has_set: bool) -> pa.Table:
    """Batches with the same float columns, gain version and gain-set column as one table of :data:`SCHEMA`."""
    n = sum(len(b) for b in group)
    values = np.concatenate([b.values for b in group]).reshape(n, len(columns)).astype(np.float64, copy=False)
    vehicles = pa.array(list(itertools.chain.from_iterable(b.vehicle_ids for b in group)), pa.string())
    levels = pa.DictionaryArray.from_arrays(pa.array(np.concatenate([b.level_codes for b in group])), _LEVELS)
    if has_set:
        fast = np.concatenate([b.fast for b in group if b.fast is not None])
        gain_set = pa.DictionaryArray.from_arrays(pa.array(np.where(fast, 0, 1).astype(np.int8)), _GAIN_SETS)
    else:
        gain_set = pa.nulls(n, SCHEMA.field("gain_set").type)
    data: dict[str, pa.Array] = {
        "vehicle": vehicles,
        "seq": pa.array(np.concatenate([b.seq for b in group]).astype(np.int64, copy=False)),
        "t_ns": pa.array(np.concatenate([b.t_ns for b in group]).astype(np.int64, copy=False)),
        "in_domain": pa.array(np.concatenate([b.in_domain for b in group]).astype(bool, copy=False)),
        "gain_version": pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([version])),
        "level": levels,
        "gain_set": gain_set,
    }
    index = {name: k for k, name in enumerate(columns)}
    for name in _FLOAT_COLUMNS:
        k = index.get(name)
        data[name] = pa.array(values[:, k]) if k is not None else pa.nulls(n, pa.float64())
    arrays = [data[name].cast(SCHEMA.field(name).type) for name in SCHEMA.names]
    return pa.Table.from_arrays(arrays, schema=SCHEMA)


class EstimateHistory:
    """The history of one replica: a writer thread and the files it keeps (module docstring)."""

    def __init__(
        self,
        directory: Path,
        replica_id: str,
        retention_s: float,
        chunk_s: float,
        precision: Literal["float64", "float32"] = "float64",
    ) -> None:
        self.directory = directory
        #: the schema files are written with: the float channels as ``precision``
        self.file_schema = SCHEMA if precision == "float64" else _FLOAT32_SCHEMA
        self.replica_id = replica_id
        self.retention_ns = round(retention_s * 1e9)
        self.chunk_ns = round(chunk_s * 1e9)
        self.convert_ns = round(CONVERT_S * 1e9)
        self.stats = HistoryStats()
        # the ticks' batches, appended by the ingest loop and taken by the writer every CONVERT_S: a deque's append
        # wakes nobody (a queue woke the writer at every tick, 2,000 hand-overs of the interpreter lock a second
        # at 1,000 vehicles, each one interrupting the ingest loop)
        self._pending: collections.deque[tuple[int, list[EstimateBatch]]] = collections.deque()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # guards _chunk, _writing, _files and stats across the writer and readers
        self._chunk: _Chunk | None = None
        #: the chunk being written, until its file is complete (its rows are read from memory meanwhile)
        self._writing: _Write | None = None
        #: written files: path -> (first, last) t_ns they hold
        self._files: dict[Path, tuple[int, int]] = {}
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Index the files already there (a restart keeps its history), then start the writer thread."""
        self.directory.mkdir(parents=True, exist_ok=True)
        for path in sorted(self.directory.glob("*/*.parquet")):
            span = _time_span(path)
            if span is not None:
                self._files[path] = span
        self.stats.bytes_on_disk = sum(_size(p) for p in self._files)
        self._thread = threading.Thread(target=self._run, name="estimate-history", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Write what is pending and stop the writer."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        self._stop.clear()

    def append(self, batches: list[EstimateBatch]) -> None:
        """Keep one tick's batches (called on the ingest loop: one deque append, nothing else)."""
        self._pending.append((time.time_ns(), batches))

    # ------------------------------------------------------------------ the writer thread

    def _run(self) -> None:
        _lower_priority(WRITER_NICE)
        pending = self._pending
        next_round = 0.0  # [s, perf_counter] when the chunk being written may take its next round
        while True:
            stopping = self._stop.wait(CONVERT_S)
            while pending:
                self._take(*pending.popleft())
            self._take(time.time_ns(), [])  # time passed: a chunk may have ended, a conversion may be due
            if stopping:
                self._finish_write()
                self._flush()
                return
            if self._writing is not None and time.perf_counter() >= next_round:  # conversions go on between rounds
                took = self._write_some()
                next_round = time.perf_counter() + min(WRITE_REST_MAX_S, WRITE_REST * took)

    def _take(self, now_ns: int, batches: list[EstimateBatch]) -> None:
        """One tick's batches into the chunk of their time; the chunk's write begun when its interval is over."""
        chunk = self._chunk
        if chunk is not None and now_ns >= chunk.start_ns + self.chunk_ns:
            self._finish_write()  # the one before, if it is not done yet
            self._begin_write()
            self._expire(now_ns)
            chunk = None
        if batches:
            with self._lock:
                if chunk is None:
                    chunk = self._chunk = _Chunk(now_ns - now_ns % self.chunk_ns, converted_ns=now_ns)
                chunk.batches.extend(batches)
                chunk.rows += sum(len(b) for b in batches)
        if chunk is not None and now_ns >= chunk.converted_ns + self.convert_ns:
            with self._lock:
                chunk.convert(now_ns)

    def _flush(self) -> None:
        """Write the current chunk whole (the writer thread, when it stops)."""
        self._begin_write()
        self._finish_write()

    def _begin_write(self) -> None:
        """Hand the current chunk to :meth:`_write_some`, which writes its file a round at a time."""
        chunk = self._chunk
        if chunk is None or not chunk.rows:
            with self._lock:
                self._chunk = None
            return
        day = time.strftime("%Y-%m-%d", time.gmtime(chunk.start_ns / 1e9))
        path = self.directory / day / f"{chunk.start_ns:019d}-{self.replica_id}.parquet"
        with self._lock:
            chunk.convert(time.time_ns())  # every row in a table: reads take them from there until the file is done
            self._writing, self._chunk = _Write(chunk, path, self._rounds(chunk, path)), None

    def _rounds(self, chunk: _Chunk, path: Path) -> Iterator[None]:
        """Write ``chunk`` to ``path``, a step at a time: each column made contiguous, the rows' order (vehicle,
        then time), then a row group at a time; the file registered at the end. Taking a row group from contiguous
        columns is cheap (a minute of 1,000 vehicles: 0.3 s for all 92 groups, against 2.8 s from the chunks)."""
        table = chunk.table()
        columns = []
        for column in table.columns:
            columns.append(column.combine_chunks())
            yield
        table = pa.Table.from_arrays(columns, schema=table.schema)
        with self._lock:
            parts, chunk.tables = chunk.tables, [table]  # reads take the rows from here now
        while parts:  # the parts' buffers go a slice at a time (module constant)
            del parts[-PARTS_FREED_PER_ROUND:]
            yield
        order = _vehicle_and_time_order(table)
        yield
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".parquet.tmp")
        try:
            with pq.ParquetWriter(tmp, self.file_schema, **_ENCODINGS) as writer:
                for start in range(0, table.num_rows, ROW_GROUP_ROWS):
                    rows = table.take(order.slice(start, ROW_GROUP_ROWS)).cast(self.file_schema)
                    writer.write_table(rows, row_group_size=ROW_GROUP_ROWS)
                    yield
            tmp.replace(path)
        except BaseException:  # a failed write, or the rounds dropped unfinished: no partial file is left
            tmp.unlink(missing_ok=True)
            raise
        span = (int(pc.min(table["t_ns"]).as_py()), int(pc.max(table["t_ns"]).as_py()))
        with self._lock:
            self._files[path] = span
            self._writing = None
            self.stats.rows_written += chunk.rows
            self.stats.files_written += 1
            self.stats.bytes_on_disk += _size(path)

    def _write_some(self) -> float:
        """One round of the chunk being written (:meth:`_rounds`); return the time it took [s]. A failed write is
        counted (:meth:`_lost`) and the writer goes on."""
        write = self._writing
        if write is None:
            return 0.0
        started = time.perf_counter()
        try:
            next(write.rounds, None)
        except (OSError, pa.ArrowException) as exc:
            with self._lock:
                self._writing = None
            self._lost(write.chunk, write.path, exc)
        return time.perf_counter() - started

    def _finish_write(self) -> None:
        """Write what is left of the chunk being written, at once."""
        while self._writing is not None:
            self._write_some()

    def _lost(self, chunk: _Chunk, path: Path, exc: Exception) -> None:
        """A chunk whose file could not be written: counted, logged, its rows dropped."""
        with self._lock:
            self.stats.write_failures += 1
            self.stats.rows_lost += chunk.rows
            self.stats.last_error = f"{path}: {exc}"
        log.error("estimate history: %s rows of %s lost: %s", chunk.rows, path.name, exc)

    def _expire(self, now_ns: int) -> None:
        """Delete the files whose interval ended before the retention (the writer thread only)."""
        cutoff = now_ns - self.retention_ns
        for path in list(self._files):
            match = _FILE_NAME.match(path.name)
            if match is None or int(match.group(1)) + self.chunk_ns > cutoff:
                continue
            size = _size(path)
            try:
                path.unlink(missing_ok=True)
                if not any(path.parent.iterdir()):
                    path.parent.rmdir()
            except OSError as exc:
                log.warning("estimate history: cannot delete %s: %s", path, exc)
                continue
            with self._lock:
                del self._files[path]
                self.stats.files_deleted += 1
                self.stats.bytes_on_disk -= size

    # ------------------------------------------------------------------ reading

    def read(self, vehicle_id: str, start_ns: int, end_ns: int, limit: int | None = None) -> pa.Table:
        """The vehicle's estimates with start_ns <= t_ns < end_ns, oldest first (at most ``limit``, the oldest)."""
        with self._lock:
            files = sorted(p for p, (low, high) in self._files.items() if high >= start_ns and low < end_ns)
            pending = list(self._chunk.batches) if self._chunk is not None else []
            converted = list(self._chunk.tables) if self._chunk is not None else []
            if self._writing is not None:  # a chunk whose file is not complete yet
                converted += self._writing.chunk.tables
        # the ticks the writer has not taken yet (deque.copy runs in C, under the interpreter lock: a consistent copy)
        pending += [b for _, batches in self._pending.copy() for b in batches]
        predicate = (pc.field("vehicle") == vehicle_id) & (pc.field("t_ns") >= start_ns) & (pc.field("t_ns") < end_ns)
        parts = []
        for path in files:
            try:
                parts.append(pq.read_table(path, filters=predicate))
            except (OSError, pa.ArrowException) as exc:  # deleted by retention meanwhile, or unreadable
                log.warning("estimate history: cannot read %s: %s", path, exc)
        parts += [t.filter(predicate) for t in converted]
        own = [b for b in pending if vehicle_id in b.vehicle_ids]
        if own:
            parts.append(batch_table(own).filter(predicate))
        if not parts:
            return SCHEMA.empty_table()
        table = pa.concat_tables([p.cast(SCHEMA) for p in parts]).unify_dictionaries()
        table = table.take(pc.sort_indices(table, sort_keys=[("t_ns", "ascending"), ("seq", "ascending")]))
        return table if limit is None else table.slice(0, limit)


def rows_table(rows: Sequence[EstimateRow], vehicle_id: str) -> pa.Table:
    """In-memory estimate rows of one vehicle (FleetEngine.estimate_history) as a table of :data:`SCHEMA`; the
    columns a row does not carry (gain version, level) are null."""
    data: dict[str, list[Any]] = {
        n: [getattr(r, n) for r in rows] for n in SCHEMA.names if n in EstimateRow.model_fields
    }
    data["vehicle"] = [vehicle_id] * len(rows)
    arrays = [
        pa.array(data[n]).cast(SCHEMA.field(n).type) if n in data else pa.nulls(len(rows), SCHEMA.field(n).type)
        for n in SCHEMA.names
    ]
    return pa.Table.from_arrays(arrays, schema=SCHEMA)


def table_rows(table: pa.Table) -> Iterator[dict[str, Any]]:
    """The rows of a history table as dicts, nulls (absent columns) left out."""
    for row in table.to_pylist():
        yield {k: v for k, v in row.items() if v is not None}


def _vehicle_and_time_order(table: pa.Table) -> pa.Array:
    """The row indices of ``table`` in the order of vehicle, then time.

    Arrow sorts no dictionary column, and sorting the ids as strings took 6.7 s of a core for a minute of 1,500
    vehicles (9 million rows): a burst that starved the ingest loop once a minute on a small machine. The
    dictionary's strings are ranked instead (a few thousand) and the rows sorted by (rank, t_ns), two integer
    columns: 1.0 s for the same minute, the same order."""
    vehicles = table["vehicle"].unify_dictionaries().combine_chunks()
    if not pa.types.is_dictionary(vehicles.type) or vehicles.null_count:
        keys = pa.table({"vehicle": vehicles.cast(pa.string()), "t_ns": table["t_ns"]})
        return pc.sort_indices(keys, sort_keys=[("vehicle", "ascending"), ("t_ns", "ascending")])
    _, rank = np.unique(vehicles.dictionary.to_numpy(zero_copy_only=False), return_inverse=True)
    keys = pa.table({"rank": pa.array(rank.astype(np.int32)[vehicles.indices.to_numpy()]), "t_ns": table["t_ns"]})
    return pc.sort_indices(keys, sort_keys=[("rank", "ascending"), ("t_ns", "ascending")])


def _time_span(path: Path) -> tuple[int, int] | None:
    """(first, last) t_ns of a history file from its footer's statistics; None for a file that is not one."""
    if _FILE_NAME.match(path.name) is None:
        return None
    try:
        meta = pq.ParquetFile(path).metadata
    except (OSError, pa.ArrowException) as exc:
        log.warning("estimate history: %s is not readable and is ignored: %s", path, exc)
        return None
    column = meta.schema.names.index("t_ns")
    lows, highs = [], []
    for g in range(meta.num_row_groups):
        stats = meta.row_group(g).column(column).statistics
        if stats is None or not stats.has_min_max:
            return None
        lows.append(int(stats.min))
        highs.append(int(stats.max))
    return (min(lows), max(highs)) if lows else None


def _lower_priority(nice: int) -> None:
    """Lower the calling thread's CPU priority by ``nice`` (Linux: a thread is a task the scheduler sees on its own).

    The writer's work comes in bursts: once a chunk's interval is over, sorting and writing a minute of 1,000
    vehicles takes a core for seconds. At the default priority that burst competes with the ingest loop (and, on a
    small machine, with the vehicles' own processes) and a window's p99 latency jumped to hundreds of ms; at a
    lower one it takes what the others leave. Most of the burst runs in Arrow with the interpreter lock released."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + nice)
    except (AttributeError, OSError) as exc:  # not Linux, or not permitted: the writer runs at the usual priority
        log.info("estimate history: the writer's priority stays as it is: %s", exc)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0

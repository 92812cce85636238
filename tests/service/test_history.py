"""The estimate history (service/history.py): every published estimate written to Parquet and read back by
vehicle and time range, files kept for the retention only, a write that fails counted with its rows and the
writer going on; and through a real service, GET /vehicles/{id}/estimates?start=&end= as JSON, CSV and Parquet."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import service.history
from agv_protocol.wire import ESTIMATE_COLUMNS, STATE_COLUMNS, Estimate, EstimateBatch, level_codes
from service.history import SCHEMA, EstimateHistory, batch_table, table_rows
from service.history_process import HistoryProcess
from tests.service.helpers import PERIOD_NS, T0_NS, make_settings, plant_measurements, probe, running, wait_for

#: history.precision float32 against the float64 estimates: relative agreement (7 significant digits)
FLOAT32_RTOL = 1e-6


def _batch(vehicles: list[str], seq: int, with_stage: bool = False) -> EstimateBatch:
    n = len(vehicles)
    columns = ESTIMATE_COLUMNS if with_stage else STATE_COLUMNS
    values = np.array([[1000.0 * i + seq + 0.25 * j for j in range(len(columns))] for i in range(n)])
    return EstimateBatch(
        vehicles,
        np.full(n, seq, dtype=np.int64),
        np.full(n, T0_NS + seq * PERIOD_NS, dtype=np.int64),
        values,
        np.ones(n, dtype=bool),
        np.zeros(n, np.int8),
        "3f9a1c0b7d2e",
        None,
        columns,
    )


def _wait_files(history: EstimateHistory, count: int) -> None:
    wait_for(lambda: history.stats.files_written >= count, what=f"{count} history files")


def test_the_history_keeps_every_estimate_and_reads_a_vehicle_back_by_time(tmp_path):
    history = EstimateHistory(tmp_path / "history", "r0", retention_s=3600.0, chunk_s=1.0)
    history.start()
    try:
        for seq in range(300):
            history.append([_batch(["a", "b", "c"], seq), _batch(["staged"], seq, with_stage=True)])
        time.sleep(1.1)
        history.append([])  # the next tick after the interval: the chunk is written
        # every row in a file (two files when the appends above took over chunk_s on a busy machine)
        wait_for(lambda: history.stats.rows_written == 1200, what="1,200 rows written")
        got = history.read("b", T0_NS + 100 * PERIOD_NS, T0_NS + 200 * PERIOD_NS)
        assert got.schema.equals(SCHEMA)
        rows = list(table_rows(got))
        assert [r["seq"] for r in rows] == list(range(100, 200))  # the range, oldest first, only that vehicle
        assert {r["vehicle"] for r in rows} == {"b"} and "torque_alpha" not in rows[0]
        assert [r["vx"] for r in rows] == [1000.0 + s for s in range(100, 200)]  # float64: exactly
        staged = list(table_rows(history.read("staged", T0_NS, T0_NS + 10 * PERIOD_NS)))
        assert len(staged) == 10 and staged[3]["steer_alpha"] == pytest.approx(3 + 0.25 * 8)
        assert Estimate.model_validate({**staged[0], "v": 1}).torque_alpha is not None  # the record's fields
        assert history.read("b", T0_NS, T0_NS + 300 * PERIOD_NS, limit=7).num_rows == 7
        assert history.stats.rows_written == 1200 and history.stats.bytes_on_disk > 0
        # rows not yet in a file are read too
        history.append([_batch(["b"], seq) for seq in range(300, 305)])
        wait_for(lambda: history.read("b", T0_NS, T0_NS + 400 * PERIOD_NS).num_rows == 305, what="pending rows read")
    finally:
        history.close()
    # each column written as _ENCODINGS says: a dictionary only where the record's column is one, byte-stream
    # split for the floats, deltas for seq and t_ns (Parquet's default tries a dictionary everywhere first)
    path = min((tmp_path / "history").rglob("*.parquet"))  # the first chunk
    chunk = pq.ParquetFile(path).metadata.row_group(0)
    encodings = {chunk.column(i).path_in_schema: set(chunk.column(i).encodings) for i in range(chunk.num_columns)}
    dictionary = {"RLE_DICTIONARY", "PLAIN_DICTIONARY"}  # (RLE alone: the definition levels of a nullable column)
    assert "RLE_DICTIONARY" in encodings["vehicle"] and "RLE_DICTIONARY" in encodings["level"]
    for name, encoding in {"vx": "BYTE_STREAM_SPLIT", "steer_alpha": "BYTE_STREAM_SPLIT",
                           "seq": "DELTA_BINARY_PACKED", "t_ns": "DELTA_BINARY_PACKED"}.items():  # fmt: skip
        assert encoding in encodings[name] and not encodings[name] & dictionary, (name, encodings[name])
    # a restart indexes the files it finds and reads them as before
    again = EstimateHistory(tmp_path / "history", "r0", retention_s=3600.0, chunk_s=1.0)
    again.start()
    try:
        assert again.read("c", T0_NS, T0_NS + 300 * PERIOD_NS).num_rows == 300
    finally:
        again.close()


def test_the_writer_keeps_converted_tables_not_batches_and_reads_and_writes_them_whole(tmp_path, monkeypatch):
    """The writer turns what it holds into Arrow tables as it goes (CONVERT_S, here every item), so no batch object
    waits for the chunk's end; the rows read before the write and the file written are every estimate, once."""
    monkeypatch.setattr(service.history, "CONVERT_S", 0.0)
    history = EstimateHistory(tmp_path / "history", "r0", retention_s=3600.0, chunk_s=60.0)
    history.start()
    try:
        for seq in range(50):
            history.append([_batch(["a", "b"], seq), _batch(["staged"], seq, with_stage=True)])
        assert history.read("a", T0_NS, T0_NS + 50 * PERIOD_NS).num_rows == 50  # read, taken by the writer or not
        wait_for(lambda: history._chunk is not None and history._chunk.rows == 150, what="every tick taken")
        wait_for(lambda: not history._chunk.batches, what="the batches converted")  # type: ignore[union-attr]
        chunk = history._chunk
        assert chunk is not None and len(chunk.tables) >= 2
        rows = list(table_rows(history.read("staged", T0_NS, T0_NS + 50 * PERIOD_NS)))
        assert [r["seq"] for r in rows] == list(range(50)) and rows[3]["steer_alpha"] == pytest.approx(3 + 0.25 * 8)
    finally:
        history.close()  # writes the chunk
    (path,) = (tmp_path / "history").glob("*/*.parquet")
    table = pq.read_table(path)
    assert table.num_rows == 150 and table.column("vehicle").to_pylist() == ["a"] * 50 + ["b"] * 50 + ["staged"] * 50
    assert table.column("seq").to_pylist()[50:100] == list(range(50))  # sorted by vehicle, then time


def test_a_chunk_is_written_a_row_group_at_a_time_while_the_writer_takes_the_next_ticks(tmp_path, monkeypatch):
    """The writer does not write a chunk's file in one burst: it orders the rows, then writes a row group per round,
    resting between rounds; meanwhile a read finds the chunk's rows in memory, and the next ticks go on into the
    next chunk and are converted as often as ever (CONVERT_S), not only between rounds. The file, once complete,
    holds every row once, by vehicle and time, a row group per round."""
    monkeypatch.setattr(service.history, "ROW_GROUP_ROWS", 50)
    monkeypatch.setattr(service.history, "CONVERT_S", 0.01)
    monkeypatch.setattr(service.history, "WRITE_REST_MAX_S", 0.1)  # the longest rest between two rounds
    monkeypatch.setattr(service.history, "WRITE_REST", 1e6)  # always that longest rest
    # a chunk's write is finished at once when the next chunk ends: 4 s, longer than the rounds' rests
    history = EstimateHistory(tmp_path / "history", "r0", retention_s=3600.0, chunk_s=4.0)
    history.start()
    try:
        for seq in range(100):  # 200 rows: a round per column, the order, 4 row groups; 0.1 s rests between
            history.append([_batch(["b", "a"], seq)])
        wait_for(lambda: history._writing is not None, what="the chunk's write begun", timeout=10)
        began = time.monotonic()
        assert history._chunk is None and history.stats.files_written == 0
        assert [r["seq"] for r in table_rows(history.read("a", T0_NS, T0_NS + 100 * PERIOD_NS))] == list(range(100))
        history.append([_batch(["c"], 100)])
        wait_for(lambda: history._chunk is not None and history._chunk.rows == 1, what="the next tick taken")
        wait_for(lambda: not history._chunk.batches, what="the next tick converted")  # type: ignore[union-attr]
        assert history._writing is not None  # still writing the first chunk
        _wait_files(history, 1)
        assert time.monotonic() - began >= 10 * 0.1  # the rounds rested, although the writer woke every 0.01 s
    finally:
        history.close()
    first = min((tmp_path / "history").glob("*/*.parquet"))
    meta = pq.ParquetFile(first).metadata
    table = pq.read_table(first)
    assert meta.num_row_groups == 4 and table.num_rows == 200
    assert table.column("vehicle").to_pylist() == ["a"] * 100 + ["b"] * 100
    assert table.column("seq").to_pylist() == list(range(100)) * 2


def test_a_table_of_mixed_batches_keeps_each_rows_columns_gain_version_and_set():
    """Batches of two gain versions, with and without the effectiveness columns, with and without a gain set: each
    row keeps its own values, and what its batch lacks is null."""
    plain, staged = _batch(["a", "b"], 1), _batch(["c"], 2, with_stage=True)
    t_ns, values = np.array([T0_NS, T0_NS]), np.ones((2, len(STATE_COLUMNS)))
    switched = EstimateBatch(
        ["d", "e"], np.array([3, 4]), t_ns, values, np.array([True, False]), level_codes(["WARN", "OK"]),
        "0123456789ab", np.array([True, False]),
    )  # fmt: skip
    table = batch_table([plain, switched, staged, _batch([], 5)])
    assert table.schema.equals(SCHEMA) and table.num_rows == 5
    rows = {r["vehicle"]: r for r in table_rows(table)}
    assert rows["a"]["gain_version"] == rows["c"]["gain_version"] == "3f9a1c0b7d2e"
    assert rows["d"]["gain_version"] == "0123456789ab" and rows["d"]["gain_set"] == "fast"
    assert rows["e"]["gain_set"] == "quiet" and rows["e"]["level"] == "OK" and not rows["e"]["in_domain"]
    assert "gain_set" not in rows["a"] and "torque_alpha" not in rows["b"]
    assert rows["b"]["vx"] == 1001.0 and rows["c"]["steer_alpha"] == pytest.approx(2 + 0.25 * 8)


def test_a_chunk_is_sorted_by_vehicle_then_time_across_tables_with_different_dictionaries():
    """The writer ranks the vehicles' dictionary instead of sorting the ids as strings: the same order."""
    import pyarrow as pa
    import pyarrow.compute as pc

    rng = np.random.default_rng(5)
    names = [f"veh-{k:03d}" for k in rng.permutation(40)]
    parts = [batch_table([_batch(list(rng.permutation(names)[:25]), seq) for seq in order])
             for order in (range(10, 20), range(0, 10), range(30, 20, -1))]  # fmt: skip
    table = pa.concat_tables(parts)
    assert len({part["vehicle"].chunk(0).dictionary.to_pylist().__repr__() for part in parts}) == 3
    ordered = table.take(service.history._vehicle_and_time_order(table))
    keys = pa.table({"vehicle": table["vehicle"].cast(pa.string()), "t_ns": table["t_ns"]})
    by_strings = table.take(pc.sort_indices(keys, sort_keys=[("vehicle", "ascending"), ("t_ns", "ascending")]))
    assert ordered["vehicle"].cast(pa.string()).to_pylist() == by_strings["vehicle"].cast(pa.string()).to_pylist()
    assert ordered["t_ns"].to_pylist() == by_strings["t_ns"].to_pylist() and ordered.num_rows == 750
    assert ordered["vehicle"].cast(pa.string()).to_pylist() == sorted(ordered["vehicle"].cast(pa.string()).to_pylist())


def test_float32_precision_halves_the_file_and_keeps_seven_digits(tmp_path):
    sizes, read_back = {}, {}
    for precision in ("float64", "float32"):
        history = EstimateHistory(tmp_path / precision, "r0", 3600.0, 1.0, precision)  # type: ignore[arg-type]
        history.start()
        try:
            rng = np.random.default_rng(0)
            for seq in range(500):
                b = _batch(["a", "b"], seq)
                b.values = rng.normal(size=b.values.shape)
                history.append([b])
            time.sleep(1.1)
            history.append([])
            wait_for(lambda h=history: h.stats.rows_written == 1000, what="every row written")  # one file, or two
            rows = history.read("a", T0_NS, T0_NS + 500 * PERIOD_NS)
            assert rows.num_rows == 500 and rows.schema.equals(SCHEMA)  # read back as the record's float64
            sizes[precision] = history.stats.bytes_on_disk
            read_back[precision] = rows["vx"].to_numpy()
        finally:
            history.close()
    np.testing.assert_allclose(read_back["float32"], read_back["float64"], rtol=FLOAT32_RTOL)
    assert not np.array_equal(read_back["float32"], read_back["float64"])  # rounded, not the same numbers
    assert sizes["float32"] < 0.7 * sizes["float64"]


def test_old_files_go_after_the_retention_and_a_failed_write_is_counted(tmp_path):
    root = tmp_path / "history"
    history = EstimateHistory(root, "r0", retention_s=1.0, chunk_s=1.0)
    history.start()
    try:
        history.append([_batch(["a"], 0)])
        time.sleep(1.1)
        history.append([])
        _wait_files(history, 1)
        (first,) = list(root.glob("*/*.parquet"))
        assert pq.read_table(first).num_rows == 1
        # the next intervals: the first file is older than the retention and is deleted
        for _ in range(3):
            history.append([_batch(["a"], 1)])
            time.sleep(1.1)
        history.append([])
        wait_for(lambda: history.stats.files_deleted >= 1, what="the expired file deleted")
        assert not first.exists()
        # the directory gone, a file in its place (a volume unmounted, say): the write fails, is counted with its
        # rows, and the writer goes on to write the next interval once the directory is back
        wait_for(lambda: history._chunk is None and history._writing is None, what="every interval before written")
        moved = tmp_path / "moved"
        root.rename(moved)
        root.write_text("not a directory")
        history.append([_batch(["a"], 2), _batch(["b"], 2)])
        time.sleep(1.1)
        history.append([])
        wait_for(lambda: history.stats.write_failures >= 1, what="the failed write counted")
        assert history.stats.rows_lost == 2 and "not a directory" in (history.stats.last_error or "").lower()
        root.unlink()
        moved.rename(root)
        written = history.stats.files_written
        history.append([_batch(["a"], 3)])
        time.sleep(1.1)
        history.append([])
        wait_for(lambda: history.stats.files_written > written, what="the next file written")
    finally:
        history.close()


@pytest.mark.parametrize("writer", ["thread", "process"])
def test_the_service_answers_a_time_range_of_estimates_as_json_csv_and_parquet(tmp_path, writer):
    """The same answers whether the history is a thread of the service or its own process (history.writer)."""
    settings = make_settings(tmp_path, history={"chunk_s": 1.0, "writer": writer})
    samples = plant_measurements(["hist-1", "hist-2"], 9000)  # 90 s of two vehicles
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        for row in samples:
            for m in row:
                p.put(m)
        wait_for(lambda: len(p.estimates_of("hist-1")) >= 9000, what="the estimates")
        time.sleep(1.2)  # one more interval: the chunk is written at the next tick
        p.put(plant_measurements(["hist-2"], 9001)[-1][0])
        wait_for(lambda: srv.service.history.stats.files_written >= 1, what="a history file")
        live = {e.seq: e for e in p.estimates_of("hist-1")}
        window = {"start": (T0_NS + 100 * PERIOD_NS) / 1e9, "end": (T0_NS + 300 * PERIOD_NS) / 1e9}
        answer = srv.get("/vehicles/hist-1/estimates", params=window).json()
        got = answer["estimates"]
        assert [r["seq"] for r in got] == list(range(100, 300))
        assert [r["torque_fault"] for r in got] == [live[r["seq"]].torque_fault for r in got]  # the published values
        # paging: at most `limit`, and a Link to the rest
        page = srv.http.get("/vehicles/hist-1/estimates", params={**window, "limit": 50})
        assert len(page.json()["estimates"]) == 50 and 'rel="next"' in page.headers["link"]
        # CSV, streamed: a header of the record's fields, one row per estimate
        text = srv.http.get("/vehicles/hist-1/estimates", params=window, headers={"Accept": "text/csv"})
        assert text.headers["content-type"].startswith("text/csv")
        rows = list(csv.DictReader(io.StringIO(text.text)))
        assert len(rows) == 200 and rows[0]["vehicle"] == "hist-1" and int(rows[-1]["seq"]) == 299
        assert "torque_alpha" not in rows[0]  # no row has it: the column is left out
        # Parquet: the same rows
        blob = srv.http.get(
            "/vehicles/hist-1/estimates", params=window, headers={"Accept": "application/vnd.apache.parquet"}
        )
        table = pq.read_table(io.BytesIO(blob.content))
        assert table.num_rows == 200 and table["seq"].to_pylist() == list(range(100, 300))
        # a download link: ?format=csv, as an attachment
        link = srv.http.get("/vehicles/hist-1/estimates", params={**window, "format": "csv"})
        assert link.headers["content-disposition"] == 'attachment; filename="hist-1-estimates.csv"'
        assert link.text == text.text
        # the whole 90 s back as CSV and as Parquet: every estimate, the values published
        whole = {"start": T0_NS / 1e9, "end": (T0_NS + 9000 * PERIOD_NS) / 1e9}
        table = pq.read_table(
            io.BytesIO(
                srv.http.get(
                    "/vehicles/hist-1/estimates", params=whole, headers={"Accept": "application/vnd.apache.parquet"}
                ).content
            )
        )
        assert table["seq"].to_pylist() == list(range(9000))
        for name in STATE_COLUMNS:
            assert table[name].to_pylist() == [getattr(live[k], name) for k in range(9000)], name
        full_csv = srv.http.get("/vehicles/hist-1/estimates", params=whole, headers={"Accept": "text/csv"}).text
        csv_rows = list(csv.DictReader(io.StringIO(full_csv)))
        assert [int(r["seq"]) for r in csv_rows] == list(range(9000))
        assert [float(r["steer_fault"]) for r in csv_rows] == [live[k].steer_fault for k in range(9000)]
        # a range with end before start is refused; without a range the in-memory window answers, as before
        bad = srv.http.get("/vehicles/hist-1/estimates", params={"start": 20.0, "end": 10.0})
        assert bad.status_code == 422 and "end must be after start" in bad.text
        recent = srv.get("/vehicles/hist-1/estimates", params={"limit": 5}).json()["estimates"]
        assert [r["seq"] for r in recent] == list(range(8995, 9000))
        metrics = srv.http.get("/metrics").text
        assert "agv_fe_history_rows_written_total" in metrics and "agv_fe_history_bytes" in metrics


def test_a_replica_without_history_says_so(tmp_path):
    with running(make_settings(tmp_path, history={"enabled": False})) as srv:
        for row in plant_measurements(["quiet-1"], 5):
            with probe(srv.settings.zenoh.endpoint) as p:
                p.put(row[0])
        wait_for(lambda: srv.http.get("/vehicles/quiet-1").status_code == 200, what="the vehicle")
        r = srv.http.get("/vehicles/quiet-1/estimates", params={"start": 0})
        assert r.status_code == 409 and "history" in r.text
    assert not Path(srv.settings.data_dir / "history").exists()


def test_a_history_process_that_dies_makes_the_replica_unready_and_reads_fail_clearly(tmp_path):
    settings = make_settings(tmp_path, history={"writer": "process"})
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        for row in plant_measurements(["gone-1"], 50):
            p.put(row[0])
        wait_for(lambda: len(p.estimates_of("gone-1")) >= 50, what="the estimates")
        whole = {"start": T0_NS / 1e9, "end": (T0_NS + 50 * PERIOD_NS) / 1e9}
        wait_for(
            lambda: len(srv.get("/vehicles/gone-1/estimates", params=whole).json()["estimates"]) == 50,
            what="the child holding every estimate",
        )
        history = srv.service.history
        assert isinstance(history, HistoryProcess) and history.alive
        history._process.kill()
        wait_for(lambda: not history.alive, what="the child gone")
        ready = srv.get("/ready").json()
        assert not ready["ready"] and "keeps the estimate history has exited" in ready["detail"]
        r = srv.http.get("/vehicles/gone-1/estimates", params=whole)
        assert r.status_code == 503 and "history process has exited" in r.json()["detail"]

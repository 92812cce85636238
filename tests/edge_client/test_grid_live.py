"""The live side of the grid rule (edge_client/grid.py): when a bridge's grid starts; a mapped road grade held and
sent like the four signals."""

from __future__ import annotations

import threading

import pytest

from edge_client.grid import COLUMNS, LiveSource
from edge_client.recording import RecordingError

FRESH = [("vx", 5.0), ("r", 0.0), ("torque", 1.0), ("steer", 0.0)]


def _source(now: list[int], wait_s: float, mapped: tuple[str, ...] = COLUMNS) -> LiveSource:
    return LiveSource("car-1", 0.01, max_age_s=0.1, wait_s=wait_s, clock=lambda: now[0], mapped=mapped)


def test_the_grid_starts_at_an_instant_every_column_is_fresh_now_not_at_one_that_passed():
    """Every column came while the publisher was still starting, then 0.2 s passed without a message: seq 0 waits
    for the next fresh instant and is a measurement (it was a stale tick, never sent)."""
    now = [0]
    source = _source(now, wait_s=30.0)
    source.received(FRESH)
    now[0] = 200_000_000  # 0.2 s on the source's clock: every column older than max_age_s
    started = threading.Event()
    waiting = threading.Thread(target=lambda: (source.prepare(), started.set()), daemon=True)
    waiting.start()
    assert not started.wait(0.3)  # the clock stands still: nothing can make the passed instant fresh
    source.received([("vx", 6.0), ("r", 0.1), ("torque", 2.0), ("steer", 0.01)])
    assert started.wait(30.0)
    tick = source.next_tick()
    assert tick.k == 0 and tick.active.tolist() == [True]
    assert tick.y.tolist() == [[6.0, 0.1]] and tick.u.tolist() == [[2.0, 0.01]]
    assert tick.grade is None  # no grade mapped: the measurement carries none
    assert source.stale_ticks == dict.fromkeys(("vx", "r", "torque", "steer"), 0)
    assert source.used_text() == "vx 2, r 2, torque 2, steer 2"


def test_a_grid_that_never_gets_a_fresh_instant_names_what_went_stale():
    now = [0]
    source = _source(now, wait_s=0.2)
    source.received(FRESH)
    source.received([("vx", 5.0)])
    now[0] = 150_000_000
    source.received([("vx", 5.1), ("r", 0.0)])  # torque and steer 0.15 s old
    with pytest.raises(RecordingError, match=r"within 0.2 s .* missing or stale: torque, steer"):
        source.prepare()


def test_a_mapped_grade_is_held_like_the_four_signals_and_a_stale_one_is_named():
    """With ``grade`` mapped, the grid waits for it too, each tick carries the latest grade received, and a grade
    older than max_age_s stops the ticks and is counted under its name, as a stale signal of the four is."""
    now = [0]
    source = _source(now, wait_s=0.2, mapped=(*COLUMNS, "grade"))
    source.received(FRESH)
    with pytest.raises(RecordingError, match=r"missing or stale: grade$"):
        source.prepare()  # the four came, the grade never did
    source.received([("grade", 0.04)])
    source.prepare()
    first = source.next_tick()
    assert first.active.tolist() == [True] and first.grade is not None and first.grade.tolist() == [0.04]
    now[0] = 50_000_000
    source.received([*FRESH, ("grade", -0.025)])
    second = source.next_tick()
    assert second.grade is not None and second.grade.tolist() == [-0.025]
    assert second.y.tolist() == [[5.0, 0.0]] and second.u.tolist() == [[1.0, 0.0]]
    now[0] = 160_000_000  # the four keep coming; the grade is 0.11 s old
    source.received(FRESH)
    stale = source.next_tick()
    assert stale.active.tolist() == [False] and (stale.k, source.sampled) == (2, 2)
    assert source.stale_ticks == {"vx": 0, "r": 0, "torque": 0, "steer": 0, "grade": 1}
    assert source.used_text() == "vx 3, r 3, torque 3, steer 3, grade 2"
    assert "ticks not sent for a stale column: grade 1" in source.describe_grid()

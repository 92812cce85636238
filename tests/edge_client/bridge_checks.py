"""What the CAN and ROS 2 tests share: the vehicle's 100 Hz pacing, and the check of a recording with the grade."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

#: Sample period of the simulated vehicles' buses [s].
PERIOD_S = 0.01


def paced_periods(counter: Any, vehicle: str, max_periods: int, go_on: Callable[[], bool]) -> Iterator[tuple[int, int]]:
    """Periods of PERIOD_S in real time, at most ``max_periods``, while ``go_on()``: (period, since), ``since`` the
    periods since the first measurement of ``vehicle`` reached ``counter`` (test_publisher.Counter), -1 before."""
    first = None
    deadline = time.monotonic()
    for period in range(max_periods):
        if not go_on():
            return
        with counter.lock:
            seen = len(counter.meas[vehicle])
        first = period if first is None and seen else first
        yield period, -1 if first is None else period - first
        deadline += PERIOD_S
        time.sleep(max(deadline - time.monotonic(), 0.0))


def assert_grade_held(plain: Any, unmapped: Any, recording: Any, grade: np.ndarray, atol: float = 0.0) -> None:
    """A source with the grade at 50 Hz beside the four signals at 100 Hz: read with a mapping without the grade
    (``unmapped``) and with it (``recording``), the grid and signals are those of the source without the grade
    (``plain``); ``recording.grade`` is ``grade`` fresh on even samples and held on odd ones (within ``atol``)."""
    for got in (unmapped, recording):
        np.testing.assert_array_equal(got.t, plain.t)
        np.testing.assert_array_equal(got.y, plain.y)
        np.testing.assert_array_equal(got.u, plain.u)
    assert unmapped.grade is None
    n = len(recording)
    assert recording.grade is not None and recording.grade.shape == (n,)
    np.testing.assert_allclose(recording.grade[::2], grade[:n:2], rtol=0.0, atol=atol)
    np.testing.assert_allclose(recording.grade[1::2], grade[: n - 1 : 2], rtol=0.0, atol=atol)

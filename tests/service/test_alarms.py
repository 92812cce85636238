"""The level detector (persistence, hysteresis) and the alarm book (latching, acknowledgement)."""

from __future__ import annotations

import numpy as np
import pytest

from service.fleet.alarms import FAULT, OK, WARN, AlarmBook, FaultLevels, LevelDetector, UnknownAlarm
from service.profiles import AlarmThresholds

MS = 1_000_000


def feed(detector: LevelDetector, values: list[float], period_ms: int = 10) -> list[int]:
    levels = []
    for k, v in enumerate(values):
        detector.update(np.array([0]), np.array([v]), np.array([k * period_ms * MS]))
        levels.append(int(detector.level[0]))
    return levels


def detector() -> LevelDetector:
    return LevelDetector(1, warn=10.0, fault=20.0, hysteresis=0.8, raise_after_ns=50 * MS, clear_after_ns=100 * MS)


def test_a_short_spike_does_not_raise():
    assert max(feed(detector(), [0.0] * 5 + [30.0] * 5 + [0.0] * 20)) == OK


def test_persistence_then_escalation():
    levels = feed(detector(), [12.0] * 10 + [25.0] * 10)
    assert levels[4] == OK and levels[5] == WARN  # 50 ms after the first sample above 10
    assert levels[14] == WARN and levels[15] == FAULT


def test_hysteresis_band_holds_the_level_and_clearing_needs_time():
    d = detector()
    feed(d, [25.0] * 10)
    assert d.level[0] == FAULT
    # 17 is below the fault threshold but inside the band (> 0.8 x 20): FAULT holds
    d2 = detector()
    levels = feed(d2, [25.0] * 10 + [17.0] * 30)
    assert set(levels[10:]) == {FAULT}
    # below 16 for 100 ms drops to WARN, below 8 for 100 ms drops to OK
    d3 = detector()
    levels = feed(d3, [25.0] * 10 + [12.0] * 15 + [1.0] * 15)
    assert levels[10 + 9] == FAULT and levels[10 + 10] == WARN
    assert levels[25 + 9] == WARN and levels[25 + 10] == OK


def test_rows_are_independent():
    d = LevelDetector(3, 10.0, 20.0, 0.8, 0, 0)
    changed = d.update(np.array([0, 2]), np.array([25.0, 12.0]), np.array([0, 0]))
    assert changed.tolist() == [0, 1] and d.level.tolist() == [FAULT, OK, WARN]


#: Fault-channel rules quick enough to show every transition in a few dozen samples of 10 ms.
QUICK_ALARMS = AlarmThresholds(
    torque_warn_nm=10.0, torque_fault_nm=20.0, steer_warn_rad=0.01, steer_fault_rad=0.02,
    raise_after_s=0.05, clear_after_s=0.1, warmup_s=0.1,
)  # fmt: skip


def test_fault_levels_wait_for_the_warm_up_and_keep_levels_across_a_restart():
    """The fault-channel rule: nothing is evaluated during the warm-up after a (re)start, the persistence runs
    from the first warm sample, a restart holds the level, and an unusable row is left alone."""
    levels = FaultLevels(2, QUICK_ALARMS)
    rows = np.array([0, 1])
    levels.restart(rows, np.array([0, 0]))
    torque_row0: list[int] = []
    for k in range(30):  # row 0: |T_f| = 30 N m from the start; row 1: |delta_f| = 0.015 rad
        t = np.full(2, k * 10 * MS)
        levels.update(rows, np.array([[30.0, 0.0], [0.0, -0.015]]), t)
        torque_row0.append(int(levels.torque.level[0]))
    # warm from 100 ms (sample 10); held 50 ms from there: FAULT at sample 15, never WARN first (both held)
    assert torque_row0[:15] == [OK] * 15 and torque_row0[15:] == [FAULT] * 15
    assert levels.steer.level.tolist() == [OK, WARN] and levels.torque.level[1] == OK
    # a restart at 300 ms keeps FAULT; in the new warm-up even values of 0 do not clear it
    levels.restart(np.array([0]), np.array([300 * MS]))
    after_restart = []
    for k in range(30, 60):
        changed = levels.update(np.array([0]), np.array([[0.0, 0.0]]), np.array([k * 10 * MS]))
        after_restart.append((len(changed), int(levels.torque.level[0])))
    # warm again from 400 ms; below both hysteresis bands for 100 ms from there: OK at 500 ms (sample 50)
    assert after_restart[:20] == [(0, FAULT)] * 20 and after_restart[20] == (1, OK)
    # an unusable (non-finite) estimate moves nothing
    before = levels.steer.level.copy()
    levels.update(rows, np.array([[np.nan, np.nan], [np.nan, np.nan]]), np.full(2, 600 * MS), np.array([False, False]))
    assert levels.steer.level.tolist() == before.tolist()


def test_fault_levels_do_not_judge_outside_the_certified_domain():
    """An uncertified sample (premise, v_y_hat or the applied angle out of the design's box) holds the level,
    forgets the persistence timer, and starts the warm-up again: a large estimate outside the box, or in the
    warm-up after it, raises nothing; the same estimate held inside the box afterwards does."""
    levels = FaultLevels(2, QUICK_ALARMS)
    rows = np.array([0, 1])
    levels.restart(rows, np.array([0, 0]))
    big = np.array([[30.0, 0.0], [30.0, 0.0]])
    torque: list[list[int]] = []
    for k in range(60):  # row 0 leaves the certified domain from 200 to 300 ms; row 1 never does
        certified = np.array([not 20 <= k < 30, True])
        levels.update(rows, big if k >= 20 else np.zeros((2, 2)), np.full(2, k * 10 * MS), None, certified)
        torque.append(levels.torque.level.tolist())
    row0, row1 = [t[0] for t in torque], [t[1] for t in torque]
    # row 1: above the thresholds from 200 ms, FAULT 50 ms later
    assert row1[24] == OK and row1[25] == FAULT
    # row 0: nothing while outside (to 290 ms) and in the warm-up after its last uncertified sample (to 390 ms);
    # then held for 50 ms: FAULT at 440 ms (sample 44)
    assert row0[:44] == [OK] * 44 and row0[44:] == [FAULT] * 16
    # a raised level is held, not cleared, outside the domain
    for k in range(60, 80):
        levels.update(rows, np.zeros((2, 2)), np.full(2, k * 10 * MS), None, np.array([False, True]))
    assert levels.torque.level.tolist() == [FAULT, OK]


class InFull(LevelDetector):
    """The detector without its shortcut for quiet rows: every row's timers and level updated in full."""

    def update(self, rows: np.ndarray, values: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        return self._update_in_full(rows, np.abs(values), t_ns)


@pytest.mark.parametrize("seed", range(4))
def test_the_shortcut_for_quiet_rows_gives_the_levels_of_the_full_update(seed):
    """Random rows and values that wander across both thresholds and back, with quiet spells and spikes: the
    detector's levels and changed rows match, sample for sample, those of updating every row in full."""
    rng = np.random.default_rng(seed)
    rows_total, settings = 12, {"warn": 10.0, "fault": 20.0, "hysteresis": 0.8}
    fast = LevelDetector(rows_total, **settings, raise_after_ns=40 * MS, clear_after_ns=70 * MS)
    full = InFull(rows_total, **settings, raise_after_ns=40 * MS, clear_after_ns=70 * MS)
    value = np.zeros(rows_total)  # each row's value: pulled towards 0 in quiet spells, towards its target otherwise
    targets = rng.uniform(-28.0, 28.0, rows_total)
    clocks = np.zeros(rows_total, dtype=np.int64)
    seen = {OK: 0, WARN: 0, FAULT: 0}
    ticks = {"all quiet": 0, "some quiet": 0, "none quiet": 0}
    for step in range(4000):
        rows = np.flatnonzero(rng.random(rows_total) < 0.6)
        if len(rows) == 0:
            continue
        if step % 400 == 0:
            targets = rng.uniform(-28.0, 28.0, rows_total)
        target = 0.0 if (step // 400) % 2 == 0 else targets[rows]
        value[rows] += 0.1 * (target - value[rows]) + rng.normal(0.0, 1.5, len(rows))
        spike = rng.random(len(rows)) < 0.01
        value[rows[spike]] = rng.uniform(-30.0, 30.0, int(spike.sum()))
        clocks[rows] += 10 * MS
        values, t_ns = value[rows].copy(), clocks[rows].copy()
        quiet = (np.abs(values) < 10.0) & (fast.level[rows] == OK)
        ticks["all quiet" if quiet.all() else "some quiet" if quiet.any() else "none quiet"] += 1
        changed = fast.update(rows, values, t_ns)
        expected = full.update(rows, values, t_ns)
        assert changed.tolist() == expected.tolist()
        assert fast.level.tolist() == full.level.tolist()
        for lvl in fast.level.tolist():
            seen[lvl] += 1
    # the run went through every level, and through ticks where all, some and none of the rows took the shortcut
    assert min(seen.values()) > 100 and min(ticks.values()) > 100, (seen, ticks)


def test_alarm_latches_until_cleared_and_acknowledged():
    book = AlarmBook()
    raised = book.raise_level("v", "p", "torque_fault", "WARN", 1, 12.0, 10.0, "m")
    assert raised is not None and raised.event.state == "raised"
    assert book.raise_level("v", "p", "torque_fault", "WARN", 2, 12.0, 10.0, "m") is None  # no news
    escalated = book.raise_level("v", "p", "torque_fault", "FAULT", 3, 22.0, 20.0, "m")
    assert escalated.record.id == raised.record.id and escalated.record.peak_level == "FAULT"
    book.acknowledge(raised.record.id, 4, "op")
    assert book.get(raised.record.id) is not None  # acknowledged but the condition holds: still latched
    cleared = book.clear("v", "torque_fault", 5)
    assert cleared.event.state == "cleared" and book.get(raised.record.id) is None
    again = book.raise_level("v", "p", "torque_fault", "WARN", 6, 12.0, 10.0, "m")
    assert again.record.id != raised.record.id  # a new occurrence is a new alarm
    with pytest.raises(UnknownAlarm):
        book.acknowledge("al-nope", 7)


def test_a_cleared_unacknowledged_alarm_is_re_raised_with_the_same_id():
    book = AlarmBook()
    first = book.raise_level("v", "p", "out_of_domain", "WARN", 1, None, None, "")
    book.clear("v", "out_of_domain", 2)
    again = book.raise_level("v", "p", "out_of_domain", "WARN", 3, None, None, "")
    assert again.record.id == first.record.id and again.record.occurrences == 2


def test_effectiveness_levels_raise_on_a_held_loss_and_clear_when_it_is_gone():
    from service.fleet.alarms import EffectivenessLevels

    alarms = AlarmThresholds(effectiveness_after_s=1.0, clear_after_s=0.5)
    levels = EffectivenessLevels(2, alarms)
    rows = np.arange(2)
    period = 10_000_000
    history = []
    # vehicle 0: torque alpha 1 for 1 s, 0.85 for 2 s, 0.7 for 2 s, back to 1; vehicle 1: steering 1.2 throughout
    for k in range(700):
        t = k * period
        a0 = 1.0 if k < 100 else 0.85 if k < 300 else 0.7 if k < 500 else 1.0
        alpha = np.array([[a0, 1.0], [1.0, 1.2]])
        levels.update(rows, alpha, np.zeros((2, 2)), np.full(2, t, dtype=np.int64))
        history.append((levels.torque.level[0], levels.steer.level[1]))
    torque = [h[0] for h in history]
    assert torque.index(WARN) == 200  # 0.85 from k = 100, held 1 s
    assert torque.index(FAULT) == 400  # 0.7 from k = 300, held 1 s
    assert torque[499] == FAULT and torque[-1] == OK  # alpha back at 1 from k = 500: cleared after 0.5 s per step
    assert {h[1] for h in history} == {OK}  # a gain above 1 is no loss
    # the thresholds are checked: FAULT below WARN
    with pytest.raises(ValueError, match="effectiveness_fault must be below effectiveness_warn"):
        AlarmThresholds(effectiveness_warn=0.8, effectiveness_fault=0.85)


def test_effectiveness_levels_compare_the_upper_confidence_bound_with_the_thresholds():
    """alpha_hat 0.8 held: alarmed only while alpha_hat + k sigma is below the threshold, with k from the settings."""
    from service.fleet.alarms import EffectivenessLevels

    alarms = AlarmThresholds(effectiveness_after_s=1.0, effectiveness_confidence_k=3.0)
    levels = EffectivenessLevels(3, alarms)
    rows = np.arange(3)
    alpha = np.full((3, 2), 0.8)
    # sigma 0.05: bound 0.95, not identified; 0.03: bound 0.89 < 0.9 (WARN); 0.005: bound 0.815 (WARN, not FAULT)
    sigma = np.array([[0.05, 0.05], [0.03, 0.03], [0.005, 0.005]])
    np.testing.assert_allclose(levels.upper_bound(alpha, sigma)[:, 0], [0.95, 0.89, 0.815])
    for k in range(150):
        levels.update(rows, alpha, sigma, np.full(3, k * 10_000_000, dtype=np.int64))
    assert levels.torque.level.tolist() == [OK, WARN, WARN] and levels.steer.level.tolist() == [OK, WARN, WARN]
    # k = 0 is the rule on alpha_hat itself: all three at WARN from the next update on (timers kept)
    levels.configure(alarms.model_copy(update={"effectiveness_confidence_k": 0.0}))
    levels.update(rows, alpha, sigma, np.full(3, 150 * 10_000_000, dtype=np.int64))
    levels.update(rows, alpha, sigma, np.full(3, 251 * 10_000_000, dtype=np.int64))
    assert levels.torque.level.tolist() == [WARN, WARN, WARN]


@pytest.mark.parametrize("k", [-0.1, 10.5, float("nan"), float("inf")])
def test_the_effectiveness_confidence_k_is_validated(k):
    with pytest.raises(ValueError, match="effectiveness_confidence_k"):
        AlarmThresholds(effectiveness_confidence_k=k)
    assert AlarmThresholds(effectiveness_confidence_k=0.0).effectiveness_confidence_k == 0.0
    assert AlarmThresholds().effectiveness_confidence_k == 3.0


def test_the_apis_alarm_is_the_stored_record_field_for_field_then_latched():
    """AlarmInfo (service/api/models.py) is derived from AlarmRecord: the fields of to_dict, in their order and
    all required, then ``latched``; an acknowledged, cleared record is answered unchanged."""
    from service.api.models import AlarmInfo

    book = AlarmBook()
    raised = book.raise_level("v", "p", "torque_fault", "FAULT", 1, 22.0, 20.0, "m")
    book.acknowledge(raised.record.id, 2, "op")
    record = book.clear("v", "torque_fault", 3).record.to_dict()
    assert list(AlarmInfo.model_fields) == [*record, "latched"]
    assert all(f.is_required() for f in AlarmInfo.model_fields.values())
    assert AlarmInfo(**record, latched=False).model_dump() == {**record, "latched": False}
    assert record["acknowledged_by"] == "op" and record["state"] == "cleared" and record["cleared_t_ns"] == 3

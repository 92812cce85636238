"""The observer bank of one profile: every vehicle's observer state in one array, stepped together.

Each vehicle of the profile owns a row (slot) of the arrays. One call of
:meth:`ProfileBank.step` advances any subset of rows by one sample with the
vectorised :func:`synth.observer.observer_step` (``switched_step`` for a switched
design), records the estimates in a per-row ring buffer and feeds the alarm
detectors. Gains are swapped with
:meth:`ProfileBank.activate`, which re-starts every row from its last
estimate at its next sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agv_protocol.wire import EFFECTIVENESS_COLUMNS, ESTIMATE_COLUMNS, STATE_COLUMNS
from service.fleet.alarms import Detector, EffectivenessLevels, FaultLevels, LevelDetector, seconds_to_ns
from service.profiles import ProfileSpec
from synth.effectiveness import EffectivenessEstimator
from synth.gains import ObserverGains
from synth.model import FloatArray, model_inputs
from synth.observer import RuntimeGains, initial_observer_state, observer_step, switched_step
from synth.params import VehicleParams

#: The estimate rows kept per sample have the record's float columns (agv_protocol.wire.ESTIMATE_COLUMNS);
#: the first _N_STATE are the observer's state and total faults, v_x, v_y, r, T_f, delta_f.
_N_EST = len(ESTIMATE_COLUMNS)
_N_STATE = len(STATE_COLUMNS)
#: The total faults' columns, T_f and delta_f, among the state columns.
FAULTS = slice(STATE_COLUMNS.index("torque_fault"), STATE_COLUMNS.index("steer_fault") + 1)
#: The effectiveness stage's columns: biases [T, delta] and effectiveness [T, delta].
BIASES = slice(ESTIMATE_COLUMNS.index("torque_bias"), ESTIMATE_COLUMNS.index("steer_bias") + 1)
ALPHAS = slice(ESTIMATE_COLUMNS.index("torque_alpha"), ESTIMATE_COLUMNS.index("steer_alpha") + 1)
#: The torque columns a payload's ratio rho scales back from the model's frame: the total fault and its bias.
_TORQUE_FAULT = STATE_COLUMNS.index("torque_fault")
_TORQUE_BIAS = ESTIMATE_COLUMNS.index("torque_bias")
_INITIAL_CAPACITY = 64


@dataclass(frozen=True)
class StepOutput:
    """Result of one batched step, rows in the order of the call.

    values : (k, len(ESTIMATE_COLUMNS)) estimates; in_domain, finite : (k,) bool; certified : (k,) bool, the
    design's certificate covers the step (synth.observer.StepResult.certified);
    restarted : (k,) bool, the row's observer was (re)initialised at this sample.
    fast : (k,) bool, the row ran the fast gain set of a switched design (None: the design has one set).
    """

    values: FloatArray
    in_domain: np.ndarray
    certified: np.ndarray
    finite: np.ndarray
    restarted: np.ndarray
    fast: np.ndarray | None = None


class ProfileBank:
    """Observer states, last estimates, estimate history and alarm detectors of one profile's vehicles."""

    def __init__(self, name: str, spec: ProfileSpec, history_samples: int) -> None:
        self.name = name
        self.spec = spec
        self.gains: ObserverGains | None = None
        self.runtime: RuntimeGains | None = None
        self.history_samples = history_samples
        cap = _INITIAL_CAPACITY
        self.capacity = cap
        self.free: list[int] = list(range(cap - 1, -1, -1))
        self.used = np.zeros(cap, dtype=bool)
        self.z = np.zeros((cap, 0))
        # switching rule of a switched design: innovation statistic and fast samples left (unused otherwise)
        self.switch_stat = np.zeros(cap)
        self.fast_left = np.zeros(cap, dtype=np.int64)
        self.last_fast = np.zeros(cap, dtype=bool)
        self.needs_init = np.ones(cap, dtype=bool)
        self.warm = np.full((cap, _N_STATE), np.nan)
        self.last_values = np.full((cap, _N_EST), np.nan)
        self.last_in_domain = np.zeros(cap, dtype=bool)
        self.last_seq = np.full(cap, -1, dtype=np.int64)
        self.last_t_ns = np.zeros(cap, dtype=np.int64)
        self.hist_values = np.zeros((cap, history_samples, _N_EST))
        self.hist_in_domain = np.zeros((cap, history_samples), dtype=bool)
        self.hist_seq = np.zeros((cap, history_samples), dtype=np.int64)
        self.hist_t_ns = np.zeros((cap, history_samples), dtype=np.int64)
        self.hist_count = np.zeros(cap, dtype=np.int64)
        # per-sample counts of each row, and the row's place in its estimate publishing cycle
        self.accepted = np.zeros(cap, dtype=np.int64)
        self.estimates = np.zeros(cap, dtype=np.int64)
        self.published = np.zeros(cap, dtype=np.int64)
        self.phase = np.zeros(cap, dtype=np.int64)
        # each row's payload [kg] (synth.model.payload_torque) and how many used rows carry one
        self.payload_kg = np.zeros(cap)
        self.loaded_rows = 0
        # the road grade of each row's last sample that carried one [rad] and that sample's seq (-1: none has)
        self.grade_rad = np.zeros(cap)
        self.grade_seq = np.full(cap, -1, dtype=np.int64)
        a = spec.alarms
        # the fault channels' detectors and warm-up rule (shared with `agv-fe replay`)
        self.faults = FaultLevels(cap, a, spec.params.sample_period_s)
        # out of domain as a one-level detector on a 0/1 signal
        self.domain = LevelDetector(
            cap, 0.5, np.inf, 1.0, seconds_to_ns(a.out_of_domain_after_s), seconds_to_ns(a.clear_after_s)
        )
        # the loss-of-effectiveness stage (spec.effectiveness.enabled; built with the gains) and its alarms
        self.stage: EffectivenessEstimator | None = None
        self.effectiveness = EffectivenessLevels(cap, a)

    # ------------------------------------------------------------------ configuration

    @property
    def torque(self) -> Detector:
        """The |T_f| detector of :attr:`faults`."""
        return self.faults.torque

    @property
    def steer(self) -> Detector:
        """The |delta_f| detector of :attr:`faults`."""
        return self.faults.steer

    @property
    def started_t_ns(self) -> np.ndarray:
        """When each row's observer last (re)started [ns] (the warm-up of :attr:`faults` runs from there)."""
        return self.faults.started_t_ns

    @property
    def version(self) -> str | None:
        return None if self.gains is None else self.gains.version

    @property
    def columns(self) -> tuple[str, ...]:
        """The float columns of this profile's estimates (the first of :data:`ESTIMATE_COLUMNS`)."""
        return STATE_COLUMNS if self.stage is None else STATE_COLUMNS + EFFECTIVENESS_COLUMNS

    def named_values(self, row: np.ndarray | list[float]) -> dict[str, float]:
        """A row of :attr:`last_values` or :meth:`history` by column name, the profile's columns only."""
        values = row.tolist() if isinstance(row, np.ndarray) else row
        return dict(zip(self.columns, values[: len(self.columns)], strict=True))

    @property
    def ready(self) -> bool:
        return self.runtime is not None

    def set_spec(self, spec: ProfileSpec) -> None:
        """New thresholds, limits and effectiveness stage (the gains are set by :meth:`activate`); a stage whose
        options changed starts every row afresh."""
        stage_changed = spec.effectiveness != self.spec.effectiveness
        self.spec = spec
        a = spec.alarms
        self.faults.configure(a)
        self.effectiveness.configure(a)
        if stage_changed and self.gains is not None:
            self._build_stage(self.gains)
        self.domain.configure(0.5, np.inf, 1.0, seconds_to_ns(a.out_of_domain_after_s), seconds_to_ns(a.clear_after_s))

    def activate(self, gains: ObserverGains, runtime: RuntimeGains | None = None) -> None:
        """Swap in new gains for every row at once.

        Each row re-starts at its next sample from its last estimate of the
        state and the faults (higher fault derivatives zero), so the estimate
        is continuous across the swap even when the fault order changes.
        """
        runtime = runtime or RuntimeGains.from_gains(gains)
        self._build_stage(gains)
        self.gains, self.runtime = gains, runtime
        self.z = np.zeros((self.capacity, runtime.state_size))
        self.warm = self.last_values[:, :_N_STATE].copy()
        self.needs_init[:] = True

    def _build_stage(self, gains: ObserverGains) -> None:
        """The effectiveness stage for these gains when the spec enables it (every row starts it afresh).

        Raises synth.errors.BadParameters for a design the stage cannot run on (the profile checks refuse
        those before they are stored)."""
        options = self.spec.effectiveness
        self.stage = EffectivenessEstimator(gains, options, self.capacity) if options.enabled else None
        self.effectiveness.reset(np.arange(self.capacity))

    # ------------------------------------------------------------------ slots

    def allocate(self) -> int:
        if not self.free:
            self._grow(2 * self.capacity)
        slot = self.free.pop()
        self.used[slot] = True
        self._clear_row(slot)
        return slot

    def release(self, slot: int) -> None:
        self.used[slot] = False
        self._clear_row(slot)
        self.free.append(slot)

    def restart(self, slot: int) -> None:
        """Re-initialise the row's observer from its next measurement (cold start)."""
        self.needs_init[slot] = True
        self.warm[slot] = np.nan

    def set_payload(self, slot: int, payload_kg: float) -> None:
        """The row's vehicle carries ``payload_kg`` (>= 0, finite) from its next sample on: the model's torque and
        the reported torque fault follow it (docs/math.md 12.5)."""
        self.loaded_rows += int(payload_kg > 0.0) - int(self.payload_kg[slot] > 0.0)
        self.payload_kg[slot] = payload_kg

    def note_grade(self, slots: np.ndarray, seq: np.ndarray, grade: FloatArray) -> None:
        """``slots`` (distinct) accepted samples ``seq`` that carried the road grades ``grade`` [rad]."""
        self.grade_rad[slots] = grade
        self.grade_seq[slots] = seq

    def _clear_row(self, slot: int) -> None:
        self.set_payload(slot, 0.0)
        self.grade_rad[slot] = 0.0
        self.grade_seq[slot] = -1
        self.needs_init[slot] = True
        self.warm[slot] = np.nan
        self.last_values[slot] = np.nan
        self.last_in_domain[slot] = False
        self.last_fast[slot] = False
        self.last_seq[slot] = -1
        self.last_t_ns[slot] = 0
        self.hist_count[slot] = 0
        self.accepted[slot] = self.estimates[slot] = self.published[slot] = self.phase[slot] = 0
        rows = np.array([slot])
        self.faults.reset(rows)
        self.domain.reset(rows)
        self.effectiveness.reset(rows)
        if self.stage is not None:
            self.stage.reset(rows)

    def _grow(self, capacity: int) -> None:
        extra = capacity - self.capacity

        def pad(a: np.ndarray, fill: float | int | bool) -> np.ndarray:
            block = np.full((extra, *a.shape[1:]), fill, dtype=a.dtype)
            return np.concatenate([a, block])

        self.used = pad(self.used, False)
        self.z = pad(self.z, 0.0)
        self.switch_stat = pad(self.switch_stat, 0.0)
        self.fast_left = pad(self.fast_left, 0)
        self.last_fast = pad(self.last_fast, False)
        self.needs_init = pad(self.needs_init, True)
        self.warm = pad(self.warm, np.nan)
        self.last_values = pad(self.last_values, np.nan)
        self.last_in_domain = pad(self.last_in_domain, False)
        self.last_seq = pad(self.last_seq, -1)
        self.last_t_ns = pad(self.last_t_ns, 0)
        self.hist_values = pad(self.hist_values, 0.0)
        self.hist_in_domain = pad(self.hist_in_domain, False)
        self.hist_seq = pad(self.hist_seq, 0)
        self.hist_t_ns = pad(self.hist_t_ns, 0)
        self.hist_count = pad(self.hist_count, 0)
        self.accepted = pad(self.accepted, 0)
        self.estimates = pad(self.estimates, 0)
        self.published = pad(self.published, 0)
        self.phase = pad(self.phase, 0)
        self.payload_kg = pad(self.payload_kg, 0.0)
        self.grade_rad = pad(self.grade_rad, 0.0)
        self.grade_seq = pad(self.grade_seq, -1)
        self.faults.grow(capacity)
        self.domain.grow(capacity)
        self.effectiveness.grow(capacity)
        if self.stage is not None:
            self.stage.grow(capacity)
        self.free.extend(range(capacity - 1, self.capacity - 1, -1))
        self.capacity = capacity

    def levels(self, slots: np.ndarray | int) -> np.ndarray:
        """Each row's level rank (alarms.LEVEL_NAMES): the highest of its torque, steering and domain detectors
        (and its effectiveness detectors when the stage runs)."""
        level = np.maximum(np.maximum(self.torque.level[slots], self.steer.level[slots]), self.domain.level[slots])
        if self.stage is None:
            return level
        return np.maximum(
            level, np.maximum(self.effectiveness.torque.level[slots], self.effectiveness.steer.level[slots])
        )

    def gain_set(self, slot: int) -> str | None:
        """'fast' or 'quiet': the set of the row's latest estimate (switched designs); None otherwise."""
        if self.runtime is None or not self.runtime.switched or self.last_seq[slot] < 0:
            return None
        return "fast" if self.last_fast[slot] else "quiet"

    def sample_counts(self, slot: int) -> dict[str, int]:
        """Samples the row accepted, estimates it made and estimates it published."""
        return {
            "accepted": int(self.accepted[slot]),
            "estimates": int(self.estimates[slot]),
            "published": int(self.published[slot]),
        }

    # ------------------------------------------------------------------ the step

    def step(
        self,
        slots: np.ndarray,
        y: FloatArray,
        u: FloatArray,
        seq: np.ndarray,
        t_ns: np.ndarray,
        grade: FloatArray | None = None,
    ) -> StepOutput:
        """Advance ``slots`` (distinct) by one sample: y (k, 2) = [v_x, r], u (k, 2) = [T_d, delta_d], finite;
        ``grade`` (k,) the road grade the samples carry [rad, + uphill] (0 where one carries none), or None."""
        rt = self.runtime
        if rt is None:
            raise RuntimeError(f"profile {self.name!r} has no active gains")
        rho = None
        stage_u = u
        if self.loaded_rows or grade is not None:  # the model's torque, and rho to scale the torque faults back
            u, stage_u, rho = self._model_input(slots, y, u, grade, rt.gains.params)
        restarted = self.needs_init[slots]
        if restarted.any():
            self._restart_rows(rt, slots, restarted, y, u, stage_u, rho, t_ns)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if rt.switched:
                z_next, stat, left, res = switched_step(
                    rt, self.z[slots], self.switch_stat[slots], self.fast_left[slots], y, u
                )
                self.switch_stat[slots] = stat
                self.fast_left[slots] = left
                self.last_fast[slots] = res.fast
            else:  # one gain set: no switching state to gather or scatter on the hot path
                z_next, res = observer_step(rt, self.z[slots], y, u)
        values = res.x_hat[:, :_N_STATE]
        finite: np.ndarray = np.asarray(np.isfinite(values).all(axis=1) & np.isfinite(z_next).all(axis=1))
        if self.stage is not None:
            fast = res.fast if rt.switched else None
            values = self._second_stage(self.stage, slots, values, finite, fast, y, stage_u)
        if rho is not None:
            values = values.copy() if values.base is not None else values  # not the step's own arrays
            values[:, _TORQUE_FAULT] /= rho
            if self.stage is not None:
                values[:, _TORQUE_BIAS] /= rho
        self.z[slots] = z_next
        good, values_good, in_domain, seq_good, t_good = slots, values, res.in_domain, seq, t_ns
        if not finite.all():
            bad = slots[~finite]
            self.needs_init[bad] = True
            self.warm[bad] = np.nan
            good, values_good, in_domain = slots[finite], values[finite], in_domain[finite]
            seq_good, t_good = seq[finite], t_ns[finite]
        width = values.shape[1]
        self.last_values[good, :width] = values_good
        self.last_in_domain[good] = in_domain
        self.last_seq[good] = seq_good
        self.last_t_ns[good] = t_good
        pos = self.hist_count[good] % self.history_samples
        self.hist_values[good, pos, :width] = values_good
        self.hist_in_domain[good, pos] = in_domain
        self.hist_seq[good, pos] = seq_good
        self.hist_t_ns[good, pos] = t_good
        self.hist_count[good] += 1
        return StepOutput(
            values=values,
            in_domain=res.in_domain,
            certified=res.certified,
            finite=finite,
            restarted=restarted,
            fast=res.fast if rt.switched else None,
        )

    def _restart_rows(
        self,
        rt: RuntimeGains,
        slots: np.ndarray,
        restarted: np.ndarray,
        y: FloatArray,
        u: FloatArray,
        stage_u: FloatArray,
        rho: FloatArray | None,
        t_ns: np.ndarray,
    ) -> None:
        """Start the observer (and the detectors, the stage) of the ``restarted`` ones of ``slots`` from this sample:
        from the last estimate where one is kept (a hand-over), else from the measurement."""
        rows = slots[restarted]
        warm = self.warm[rows]
        has_warm = ~np.isnan(warm).any(axis=1)
        x0 = np.zeros((len(rows), 3 + 2))
        x0[:, 0] = y[restarted, 0]
        x0[:, 2] = y[restarted, 1]
        x0[has_warm] = warm[has_warm]
        if rho is not None:  # the last estimate's torque fault in the model's frame
            x0[:, 3] *= rho[restarted]
        self.z[rows] = initial_observer_state(rt, y[restarted], x0, u[restarted])
        self.switch_stat[rows] = 0.0
        self.fast_left[rows] = rt.start_samples
        self.needs_init[rows] = False
        self.warm[rows] = np.nan
        self.faults.restart(rows, t_ns[restarted])
        self.domain.reset(rows, keep_level=True)
        self.effectiveness.reset(rows, keep_level=True)
        if self.stage is not None:
            self.stage.reset(rows, stage_u[restarted])

    def _model_input(
        self, slots: np.ndarray, y: FloatArray, u: FloatArray, grade: FloatArray | None, params: VehicleParams
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """The demand with the model's torque for the rows' payloads and the samples' road grades
        (synth.model.payload_torque); the same without the grade's part, which the effectiveness stage scales
        (a loss of effectiveness scales the torque the actuator delivers, not the grade's); and rho, None when none
        of these rows carries a payload."""
        payload = self.payload_kg[slots]
        loaded = bool(self.loaded_rows) and bool(payload.any())
        graded = grade is not None and bool(grade.any())
        if not loaded and not graded:
            return u, u, None
        return model_inputs(y, u, payload if loaded else None, grade if graded else None, params)

    def _second_stage(
        self,
        stage: EffectivenessEstimator,
        slots: np.ndarray,
        state: FloatArray,
        finite: np.ndarray,
        fast: np.ndarray | None,
        y: FloatArray,
        u: FloatArray,
    ) -> FloatArray:
        """The estimates with the effectiveness stage's columns: total faults in place of the observer's, then
        biases and effectiveness. Rows the observer lost (non-finite) restart the stage and stay NaN."""
        values = np.full((len(slots), len(STATE_COLUMNS) + len(EFFECTIVENESS_COLUMNS)), np.nan)
        values[:, :_N_STATE] = state
        ok = finite if not finite.all() else slice(None)
        rows = slots[ok]
        second = stage.step_rows(rows, state[ok, FAULTS], None if fast is None else fast[ok], y[ok], u[ok])
        values[ok, FAULTS] = second.total
        values[ok, BIASES] = second.bias
        values[ok, ALPHAS] = second.alpha
        if not finite.all():
            stage.reset(slots[~finite])
        return values

    def history(self, slot: int, limit: int) -> list[tuple[int, int, bool, list[float]]]:
        """The last ``limit`` estimates of a row, oldest first: (seq, t_ns, in_domain, values)."""
        count = int(self.hist_count[slot])
        n = min(count, self.history_samples, limit)
        out = []
        for k in range(count - n, count):
            pos = k % self.history_samples
            out.append(
                (
                    int(self.hist_seq[slot, pos]),
                    int(self.hist_t_ns[slot, pos]),
                    bool(self.hist_in_domain[slot, pos]),
                    self.hist_values[slot, pos].tolist(),
                )
            )
        return out

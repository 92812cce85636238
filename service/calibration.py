"""A complete vehicle profile from healthy recordings: identification, design, thresholds.

``agv-fe calibrate`` and ``POST /profiles/{name}/calibration`` both run
:func:`calibrate_profile`:

1. identify the vehicle parameters, the operating box and the sensor noise
   (synth.calibration: grey-box least squares with confidence intervals);
2. design the default observer for them, with the measured sensor noise in
   its noise model (synth.design);
3. replay the healthy recordings through that observer and set each fault
   channel's WARN and FAULT thresholds from the healthy estimates for a stated
   false-alarm rate (:func:`fault_thresholds`), next to the certified error
   bound of the design, and above what a stated wind gust makes the observer
   report on the identified model (:func:`gust_drives`); and measure the
   healthy spread of the estimates' block means, which the CUSUM rule
   (``alarms.rule`` 'cusum', service.fleet.cusum) normalises by;
4. say what the thresholds cost: the smallest bias each channel then
   detects, with a warning when it would hide a fault of 10 % of the nominal
   drive torque or of 0.02 rad of steering.

The result is a :class:`~service.profiles.ProfileSpec` (params, bounds,
design, alarms), the body ``PUT /profiles/{name}`` takes and the file
``synth --params`` and ``replay --params`` read.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import scipy.stats

from service.profiles import AlarmThresholds, ProfileSpec
from synth.calibration import CalibrationOptions, CalibrationResult, Drive, calibrate
from synth.design import synthesize
from synth.effectiveness import EffectivenessObserver
from synth.gains import ObserverGains
from synth.model import FloatArray, model_inputs, rk4_step
from synth.observer import FuzzyObserver
from synth.options import DesignOptions, EffectivenessOptions, NoiseModel
from synth.params import OperatingBounds, VehicleParams

#: The paper's profile's m_eff R_w [kg m]: the default noise model's torque rates and scales are tuned for it.
PAPER_TORQUE_SCALE_KGM = 443.0
#: The nominal drive torque, when not given, is that of this acceleration [m/s^2].
NOMINAL_ACCEL_MPS2 = 2.0
#: Faults every profile must be able to see: a torque bias of this share of the nominal drive torque, and a
#: steering bias of this angle [rad].
REQUIRED_TORQUE_SHARE = 0.10
REQUIRED_STEER_RAD = 0.02
#: The certified decay rates per sample calibration chooses from (without one in the design options): the
#: fastest certified rate that the wide DMVT bounds of the cornering drag allow costs noise, so calibration
#: keeps the one whose healthy residuals let the smallest faults through the thresholds.
DECAY_RATE_CANDIDATES = (0.994, 0.997, 0.999)
#: FAULT thresholds are this multiple of the WARN thresholds.
FAULT_OVER_WARN = 1.6
#: The thresholds stay at least this far above the largest healthy excursion that lasted the persistence time.
PEAK_MARGIN = 1.25
#: ... and WARN is at least this share of the fault the channel must see: a couple of minutes of recordings
#: cannot show every condition the vehicle will meet (a harder corner, another load), and a WARN at a quarter
#: of the required fault still detects it with room to spare (FAULT then sits at 40 % of it).
REQUIRED_SHARE_FLOOR = 0.25
#: The wind gust a healthy vehicle rides through without an alarm: a lateral force F_w [N] (the model's wind
#: input, a yaw moment of F_w times a 1 m arm: D_v of eq. 3) held for GUST_S [s]. 800 N for 2 s is the strongest
#: gust of the project's simulated fleets and the paper's Scenario 1 gust. With v_x and r measured, a gust's yaw
#: moment looks like a steering fault of M / (2 l_f C_f) while it lasts: the steering WARN stays PEAK_MARGIN
#: above what the observer reports for it (:func:`gust_drives`), or a gust would be a false alarm.
GUST_N = 800.0
GUST_S = 2.0
#: A gust whose held response on a fault estimate is within this many healthy sigmas makes no bias step the
#: effectiveness stage tests for (:func:`jump_size`).
JUMP_NOISE_SIGMAS = 3.0
CHANNELS = ("torque", "steer")
UNITS = {"torque": "N m", "steer": "rad"}


@dataclass(frozen=True)
class ChannelThresholds:
    """One fault channel: the healthy statistics, the thresholds, and what they let through.

    sigma : RMS of the healthy fault estimate after the warm-up [N m or rad]
    healthy_peak : the largest |estimate| the healthy recordings held for the alarm's persistence time
    certified_rms : the design's certified bound on the RMS estimation error under its noise model
    warn, fault : the thresholds
    smallest_warn_bias, smallest_fault_bias : the smallest bias that holds the estimate above WARN / FAULT
        through its noise (threshold + 2 sigma)
    required_bias : the fault the channel must be able to see (10 % of the nominal torque, 0.02 rad)
    gust_peak : the largest |estimate| a stated wind gust held for the persistence time on the identified model
        (0 when none was stated)
    set_by : what set WARN: "noise" (the Gaussian tail), "held peak", "gust" or "floor"
    """

    sigma: float
    healthy_peak: float
    certified_rms: float
    warn: float
    fault: float
    smallest_warn_bias: float
    smallest_fault_bias: float
    required_bias: float
    gust_peak: float = 0.0
    set_by: str = "noise"

    @property
    def hides_required_fault(self) -> bool:
        return self.smallest_fault_bias > self.required_bias


@dataclass(frozen=True)
class CalibrationReport:
    """Everything ``agv-fe calibrate`` prints, and the profile it writes."""

    profile: ProfileSpec
    calibration: CalibrationResult
    gains: ObserverGains
    thresholds: dict[str, ChannelThresholds]
    nominal_torque_nm: float
    false_alarms_per_1000_h: float
    warnings: list[str] = field(default_factory=list)
    #: the wind gust [N], held GUST_S, the thresholds ride through (0: none stated)
    gust_n: float = GUST_N

    def profile_document(self) -> dict[str, Any]:
        """The profile as JSON: complete params, bounds, design options and alarms."""
        return self.profile.model_dump(mode="json")

    def summary(self) -> dict[str, Any]:
        """A JSON-ready account of the calibration (parameters with intervals, residuals, thresholds)."""
        cal = self.calibration
        return {
            "duration_s": cal.duration_s,
            "peak_lateral_accel_mps2": cal.peak_lateral_accel_mps2,
            "estimates": {
                name: {"value": e.value, "ci95": [e.low, e.high], "identified": e.identified}
                for name, e in cal.estimates.items()
            },
            "sensor_noise": cal.noise,
            "residuals": cal.residuals,
            "steer_offset_rad": cal.steer_offset_rad,
            "gain_version": self.gains.version,
            "certified_decay_rate": self.gains.certificate.decay_rate,
            "nominal_torque_nm": self.nominal_torque_nm,
            "false_alarms_per_1000_h": self.false_alarms_per_1000_h,
            "gust": {"force_n": self.gust_n, "duration_s": GUST_S},
            "thresholds": {name: vars(t) | {"unit": UNITS[name]} for name, t in self.thresholds.items()},
            "warnings": list(self.warnings),
            "notes": list(cal.notes),
        }


def noise_model(result: CalibrationResult) -> NoiseModel:
    """The design's noise model for a calibrated vehicle: the measured sensor sigmas, and the default torque
    rates and scales carried over in acceleration terms (they were tuned for m_eff R_w = 443 kg m)."""
    params = result.params
    ratio = params.effective_mass_kg * params.wheel_radius_m / PAPER_TORQUE_SCALE_KGM
    default = NoiseModel()
    return default.model_copy(
        update={
            "vx_sigma_mps": result.noise["vx_sigma_mps"],
            "r_sigma_radps": result.noise["r_sigma_radps"],
            "torque_fault_rate_nm_per_s": default.torque_fault_rate_nm_per_s * ratio,
            "torque_fault_scale_nm": default.torque_fault_scale_nm * ratio,
        }
    )


def calibrate_profile(
    drives: Sequence[Drive],
    base: dict[str, Any],
    *,
    design: dict[str, Any] | None = None,
    alarms: dict[str, Any] | None = None,
    bounds: dict[str, Any] | None = None,
    nominal_torque_nm: float | None = None,
    false_alarms_per_1000_h: float = 1.0,
    gust_n: float = GUST_N,
    effectiveness: bool = False,
    description: str = "",
    options: CalibrationOptions | None = None,
    progress: Callable[[str], None] | None = None,
) -> CalibrationReport:
    """Identify, design and set thresholds; raise synth.calibration.CalibrationRefused or a SynthesisError.

    base : vehicle parameters a data sheet gives (synth.calibration.REQUIRED_BASE_FIELDS at least);
    design : design options to keep (the noise model's sensor sigmas are replaced by the measured ones);
    alarms : alarm settings to keep (persistence, warm-up...; the four fault thresholds are set here);
    bounds : an operating box to keep (OperatingBounds fields), widened to hold the recordings (:func:`stated_bounds`);
    nominal_torque_nm : the drive torque a 10 % fault is measured against (default: m_eff R_w 2 m/s^2);
    gust_n : the lateral wind gust [N] (held GUST_S) the vehicle must ride through without an alarm; 0: none.
    effectiveness : enable the loss-of-effectiveness stage in the profile, and set the fault thresholds from the
    stage's total faults on the same drives and gusts (they vary more than the observer's own estimates).
    progress : called with a line of text as each stage ends (a command shows them; the stages take seconds each).
    """
    if not (false_alarms_per_1000_h > 0 and math.isfinite(false_alarms_per_1000_h)):
        raise ValueError(f"false_alarms_per_1000_h must be positive, got {false_alarms_per_1000_h}")
    say = progress or (lambda _line: None)
    result = stated_bounds(calibrate(drives, base, options), bounds)  # a graded drive's fits on level ground
    say(f"parameters identified from {result.duration_s:.0f} s of driving")
    params = result.params
    chosen = dict(design or {})
    noise = noise_model(result)
    if isinstance(chosen.get("noise"), dict):
        noise = noise.model_copy(update={k: v for k, v in chosen["noise"].items() if "sigma" not in k})
    chosen["noise"] = noise.model_dump()
    alarm_base = AlarmThresholds.model_validate(alarms or {})
    nominal = nominal_torque_nm or params.effective_mass_kg * params.wheel_radius_m * NOMINAL_ACCEL_MPS2
    gusts = gust_drives(params, result.bounds, gust_n)
    gains, thresholds, estimates = _best_design(
        result, chosen, drives, gusts, alarm_base, false_alarms_per_1000_h, nominal, say
    )
    # the effectiveness stage's measurement noise: the observer's healthy RMS, its bias steps: the gust's (the
    # stage stays off unless asked)
    stage = EffectivenessOptions(
        enabled=effectiveness,
        torque_sigma_nm=_round_up(max(thresholds["torque"].sigma, 1e-6)),
        steer_sigma_rad=_round_up(max(thresholds["steer"].sigma, 1e-9)),
        torque_jump_nm=jump_size(thresholds["torque"]),
        steer_jump_rad=jump_size(thresholds["steer"]),
    )
    if effectiveness:  # the alarms then watch the stage's totals: thresholds from those
        estimates = healthy_fault_estimates(gains, drives, alarm_base.warmup_s, stage)
        gust = held_peaks(effectiveness_stepper(gains, stage), gusts, alarm_base.raise_after_s)
        thresholds = channel_thresholds(gains, estimates, gust, alarm_base, false_alarms_per_1000_h, nominal)
        say("thresholds set from the effectiveness stage's total faults")
    warnings = [_hiding(channel, t, nominal) for channel, t in thresholds.items() if t.hides_required_fault]
    alarm_settings = _alarm_settings(alarm_base, thresholds, estimates, params.sample_period_s)
    profile = ProfileSpec(
        description=description
        or f"calibrated from {len(drives)} recording(s), {result.duration_s:.0f} s of healthy driving",
        params=params,
        bounds=result.bounds,
        design=gains.options,
        alarms=AlarmThresholds.model_validate(alarm_settings.model_dump()),
        effectiveness=stage,
    )
    return CalibrationReport(
        profile=profile,
        calibration=result,
        gains=gains,
        thresholds=thresholds,
        nominal_torque_nm=nominal,
        false_alarms_per_1000_h=false_alarms_per_1000_h,
        warnings=warnings,
        gust_n=gust_n,
    )


def _alarm_settings(
    alarm_base: AlarmThresholds,
    thresholds: dict[str, ChannelThresholds],
    estimates: FloatArray,
    sample_period_s: float,
) -> AlarmThresholds:
    """``alarm_base`` with the four fault thresholds set here and the CUSUM's block sigmas of the healthy fault
    estimates ``estimates`` (k, 2) [N m, rad], sampled every ``sample_period_s`` [s]."""
    block_n = max(1, round(alarm_base.cusum_block_s / sample_period_s))
    return alarm_base.model_copy(
        update={
            "torque_block_sigma_nm": block_sigma(estimates[:, 0], block_n),
            "steer_block_sigma_rad": block_sigma(estimates[:, 1], block_n),
            "torque_warn_nm": thresholds["torque"].warn,
            "torque_fault_nm": thresholds["torque"].fault,
            "steer_warn_rad": thresholds["steer"].warn,
            "steer_fault_rad": thresholds["steer"].fault,
        }
    )


def _best_design(
    result: CalibrationResult,
    chosen: dict[str, Any],
    drives: Sequence[Drive],
    gusts: list[Drive],
    alarm_base: AlarmThresholds,
    false_alarms_per_1000_h: float,
    nominal: float,
    say: Callable[[str], None],
) -> tuple[ObserverGains, dict[str, ChannelThresholds], FloatArray]:
    """The design among the decay-rate candidates (or the one rate ``chosen`` names) whose thresholds detect the
    smallest faults, each relative to the fault its channel must see; with its thresholds and healthy estimates."""
    rates = [chosen["robust_decay_rate"]] if "robust_decay_rate" in chosen else list(DECAY_RATE_CANDIDATES)
    candidates: list[tuple[float, ObserverGains, dict[str, ChannelThresholds], FloatArray]] = []
    for rate in rates:
        design_options = DesignOptions.model_validate({**chosen, "robust_decay_rate": rate})
        gains = synthesize(result.params, result.bounds, design_options)
        estimates = healthy_fault_estimates(gains, drives, alarm_base.warmup_s)
        gust = held_peaks(observer_stepper(gains), gusts, alarm_base.raise_after_s)
        thresholds = channel_thresholds(gains, estimates, gust, alarm_base, false_alarms_per_1000_h, nominal)
        score = sum(t.smallest_fault_bias / t.required_bias for t in thresholds.values())
        candidates.append((score, gains, thresholds, estimates))
        say(
            f"observer designed and replayed at decay rate {rate:g} ({len(candidates)} of {len(rates)}): smallest "
            f"faults detected at {score / len(thresholds):.2f} of the required on average"
        )
    _, gains, thresholds, estimates = min(candidates, key=lambda candidate: candidate[0])
    return gains, thresholds, estimates


def calibrate_from_base(
    drives: Sequence[Drive],
    base: dict[str, Any],
    *,
    nominal_torque_nm: float | None = None,
    false_alarms_per_1000_h: float = 1.0,
    gust_n: float = GUST_N,
    effectiveness: bool = False,
    progress: Callable[[str], None] | None = None,
) -> CalibrationReport:
    """:func:`calibrate_profile` with a base document: {"params": {...}, "bounds"?, "design"?, "alarms"?,
    "description"?}."""
    return calibrate_profile(
        drives,
        base["params"],
        design=base.get("design"),
        alarms=base.get("alarms"),
        bounds=base.get("bounds"),
        nominal_torque_nm=nominal_torque_nm,
        false_alarms_per_1000_h=false_alarms_per_1000_h,
        gust_n=gust_n,
        effectiveness=effectiveness,
        description=str(base.get("description", "")),
        progress=progress,
    )


_LOWER_LIMITS = frozenset({"vx_min_mps", "vy_min_mps", "r_min_radps"})


def stated_bounds(result: CalibrationResult, given: dict[str, Any] | None) -> CalibrationResult:
    """``result`` with the operating box a vehicle engineer states (``given``: any OperatingBounds fields) kept
    and widened where the recordings' box (:func:`synth.calibration.operating_bounds`) goes beyond it: each
    limit the wider of the two, so that the recordings the thresholds are set from stay in the certified domain.
    ``given`` None or empty: ``result`` as it is.

    A wider box than the recordings need is a choice: the certificate then covers tighter turns and lower
    speeds (no out-of-domain stretch there, docs/math.md section 8), at the price of noisier estimates (the
    bounds of the DMVT terms grow). Raises ValueError (pydantic's) for an invalid box.
    """
    if not given:
        return result
    if not isinstance(given, dict):
        raise ValueError(f"bounds must be an object of OperatingBounds fields, got {type(given).__name__}")
    recorded = result.bounds
    stated = OperatingBounds.model_validate({**recorded.model_dump(), **given})
    merged: dict[str, Any] = {}
    for name in OperatingBounds.model_fields:
        mine, theirs = getattr(stated, name), getattr(recorded, name)
        if mine is None or theirs is None:
            merged[name] = theirs if mine is None else mine
        else:
            merged[name] = min(mine, theirs) if name in _LOWER_LIMITS else max(mine, theirs)
    box = OperatingBounds.model_validate(merged)
    widened = sorted(name for name in given if merged.get(name) != getattr(stated, name))
    note = "operating box: the base's bounds kept" + (
        f", widened to hold the recordings in {', '.join(widened)}" if widened else ""
    )
    return dataclasses.replace(result, bounds=box, notes=[*result.notes, note])


def channel_thresholds(
    gains: ObserverGains,
    estimates: FloatArray,
    gust: FloatArray,
    alarms: AlarmThresholds,
    false_alarms_per_1000_h: float,
    nominal_torque_nm: float,
) -> dict[str, ChannelThresholds]:
    """:func:`fault_thresholds` of each channel from its healthy estimates (K, 2) and gust peaks (2,)."""
    return {
        channel: fault_thresholds(
            estimates[:, i],
            certified_rms(gains, i),
            sample_period_s=gains.params.sample_period_s,
            persistence_s=alarms.raise_after_s,
            false_alarms_per_1000_h=false_alarms_per_1000_h,
            required_bias=nominal_torque_nm * REQUIRED_TORQUE_SHARE if channel == "torque" else REQUIRED_STEER_RAD,
            gust_peak=float(gust[i]),
        )
        for i, channel in enumerate(CHANNELS)
    }


def healthy_fault_estimates(
    gains: ObserverGains, drives: Sequence[Drive], warmup_s: float, stage: EffectivenessOptions | None = None
) -> FloatArray:
    """The fault estimates [T_f, delta_f] over the healthy drives, each after its warm-up, (K, 2): the observer's,
    or with an enabled ``stage`` the loss-of-effectiveness stage's total faults. A drive with a road grade or a
    payload is stepped as the service steps the samples of a vehicle that reported them (synth.model.model_inputs:
    the observer on the level-ground torque of the vehicle without the payload, the stage on the torque sent
    without the payload; the torque fault scaled back by rho)."""
    make = observer_stepper(gains) if stage is None or not stage.enabled else effectiveness_stepper(gains, stage)
    parts = []
    for drive in drives:
        u, stage_u, rho = drive.u, drive.u, None
        graded = drive.grade is not None and not drive.leveled
        if graded or drive.payload_kg > 0.0:
            payload = drive.payload_kg if drive.payload_kg > 0.0 else None
            u, stage_u, rho = model_inputs(drive.y, drive.u, payload, drive.grade if graded else None, gains.params)
        observer = make(drive.y[:1], u[:1])
        faults = np.empty((len(drive), 2))
        for k in range(len(drive)):
            y_k, u_k = drive.y[k : k + 1], u[k : k + 1]
            step = (
                observer.step(y_k, u_k, stage_u[k : k + 1])
                if isinstance(observer, EffectivenessObserver)
                else observer.step(y_k, u_k)
            )
            faults[k] = step.faults[0]
        if rho is not None:  # at the vehicle's scale, as the service reports it
            faults[:, 0] /= rho
        start = round(warmup_s / gains.params.sample_period_s)
        parts.append(faults[start:])
    return np.concatenate(parts) if parts else np.zeros((0, 2))


class Stepper(Protocol):
    """A batch fault estimator: ``step(y, u)`` returns an output whose ``faults`` is (n, 2) [N m, rad]."""

    def step(self, y: FloatArray, u: FloatArray) -> Any: ...


#: Makes a :class:`Stepper` for n vehicles from their first measurement and demand, y0 and u0 (n, 2).
StepperFactory = Callable[[FloatArray, FloatArray], Stepper]


def observer_stepper(gains: ObserverGains) -> StepperFactory:
    """The fuzzy observer with these gains as a :data:`StepperFactory`."""

    def make(y0: FloatArray, u0: FloatArray) -> Stepper:
        return FuzzyObserver(gains, y0, None, u0)

    return make


def effectiveness_stepper(gains: ObserverGains, stage: EffectivenessOptions) -> StepperFactory:
    """The fuzzy observer with its loss-of-effectiveness stage as a :data:`StepperFactory` (total faults)."""

    def make(y0: FloatArray, u0: FloatArray) -> Stepper:
        return EffectivenessObserver(gains, stage, y0, None, u0)

    return make


def gust_drives(
    params: VehicleParams,
    bounds: OperatingBounds,
    gust_n: float = GUST_N,
    gust_s: float = GUST_S,
    substeps: int = 10,
) -> list[Drive]:
    """Noise-free straight drives of the model at the box's lowest, middle and highest speed, each meeting a gust
    of +gust_n and one of -gust_n [N] for gust_s [s] from 0.5 s, and 2 s of calm after it ([] when gust_n is 0).

    The drive torque holds the speed (R_w (C_x v^2 + F_r)) and the steering demand is 0, so whatever the
    estimators report is the gust's doing. RK4 with ``substeps`` steps per sample.
    """
    if not (math.isfinite(gust_n) and gust_n >= 0.0 and math.isfinite(gust_s) and gust_s > 0.0):
        raise ValueError(f"a gust needs a finite force >= 0 and length > 0, got {gust_n} N for {gust_s} s")
    if gust_n == 0.0:
        return []
    s = params.sample_period_s
    speeds = np.repeat(np.linspace(bounds.vx_min_mps, bounds.vx_max_mps, 3), 2)
    sign = np.tile([1.0, -1.0], 3)
    torque = params.wheel_radius_m * (params.longitudinal_drag_coeff * speeds**2 + params.rolling_resistance_n)
    u = np.column_stack([torque, np.zeros_like(speeds)])
    n = round((0.5 + gust_s + 2.0) / s)
    t = np.arange(n) * s
    on = (t >= 0.5 - 1e-9) & (t < 0.5 + gust_s - 1e-9)
    x: FloatArray = np.column_stack([speeds, np.zeros_like(speeds), np.zeros_like(speeds)])
    no_fault = np.zeros_like(u)
    y = np.empty((n, speeds.size, 2))
    for k in range(n):
        y[k] = x[:, [0, 2]]
        wind = sign * gust_n * float(on[k])
        for _ in range(substeps):
            x = rk4_step(x, u, wind, no_fault, params, s / substeps)
    return [
        Drive(t, y[:, j].copy(), np.tile(u[j], (n, 1)), name=f"gust {sign[j] * gust_n:+g} N at {speeds[j]:g} m/s")
        for j in range(speeds.size)
    ]


def held_peaks(make: StepperFactory, drives: Sequence[Drive], persistence_s: float) -> FloatArray:
    """The largest |fault estimate| per channel [N m, rad] an estimator held for ``persistence_s`` on any of the
    drives (of equal length, run as one batch from their first samples), (2,); zeros without drives."""
    if not drives:
        return np.zeros(2)
    y = np.stack([d.y for d in drives], axis=1)
    u = np.stack([d.u for d in drives], axis=1)
    estimator = make(y[0], u[0])
    faults = np.empty(y.shape)
    for k in range(y.shape[0]):
        faults[k] = np.asarray(estimator.step(y[k], u[k]).faults)
    period = float(drives[0].t[1] - drives[0].t[0]) if len(drives[0]) > 1 else 1.0
    window = max(1, round(persistence_s / period))
    magnitude = np.abs(faults)
    if magnitude.shape[0] < window:
        return np.zeros(2)
    held = np.lib.stride_tricks.sliding_window_view(magnitude, window, axis=0).min(axis=-1)
    return np.asarray(held.max(axis=(0, 1)), dtype=float)


def block_sigma(estimate: FloatArray, block_n: int) -> float:
    """The RMS of the means of ``estimate`` over blocks of ``block_n`` samples: the healthy spread the CUSUM rule
    normalises by (service.fleet.cusum); never below a millionth of the estimate's RMS (a positive number)."""
    x = np.asarray(estimate, dtype=float)
    blocks = x[: x.size - x.size % block_n].reshape(-1, block_n).mean(axis=1) if x.size >= block_n else x
    rms = float(np.sqrt(np.mean(x**2))) if x.size else 1.0
    spread = float(np.sqrt(np.mean(blocks**2))) if blocks.size else rms
    return max(spread, 1e-6 * rms, np.finfo(float).tiny)


def certified_rms(gains: ObserverGains, channel: int) -> float:
    """The RMS error of one reported fault the design certifies under its noise model: scale * sqrt(H2 bound).

    The bound covers the weighted sum over both channels, every operating point and every rho, so it is an
    upper bound per channel too. NaN for designs without a cost bound (the paper's)."""
    bound = gains.certificate.performance.get("h2_cost_bound")
    if bound is None:
        return float("nan")
    noise = gains.options.noise
    scale = noise.torque_fault_scale_nm if channel == 0 else noise.steer_fault_scale_rad
    return float(scale * math.sqrt(bound))


def fault_thresholds(
    estimate: FloatArray,
    certified: float,
    *,
    sample_period_s: float,
    persistence_s: float,
    false_alarms_per_1000_h: float,
    required_bias: float,
    gust_peak: float = 0.0,
) -> ChannelThresholds:
    """WARN and FAULT for one channel from its healthy estimates, for a stated false-alarm rate.

    An alarm needs |estimate| >= WARN without a break for ``persistence_s``. Model the healthy estimate as
    Gaussian with its RMS sigma and count one chance per persistence window: n = 3600 / persistence_s an hour.
    For a rate lambda per hour, P(|e| >= WARN) = 2 Q(WARN / sigma) <= lambda / n. WARN is that, and never
    below PEAK_MARGIN times the largest excursion the recordings held for the persistence time (a
    recording longer than its Gaussian tail), nor below PEAK_MARGIN times ``gust_peak`` (what a stated wind
    gust held, :func:`held_peaks` of :func:`gust_drives`), nor below REQUIRED_SHARE_FLOOR of the fault the
    channel must detect (what the recordings did not show). FAULT = FAULT_OVER_WARN x WARN.
    """
    magnitude = np.abs(np.asarray(estimate, dtype=float))
    sigma = float(np.sqrt(np.mean(magnitude**2))) if magnitude.size else 0.0
    window = max(1, round(persistence_s / sample_period_s))
    held = _running_min(magnitude, window)
    peak = float(held.max()) if held.size else 0.0
    per_hour = false_alarms_per_1000_h / 1000.0
    chances = 3600.0 / max(persistence_s, sample_period_s)
    z = float(scipy.stats.norm.isf(per_hour / chances / 2.0))
    candidates = {
        "noise": z * sigma,
        "held peak": PEAK_MARGIN * peak,
        "gust": PEAK_MARGIN * gust_peak,
        "floor": REQUIRED_SHARE_FLOOR * required_bias,
    }
    set_by = max(candidates, key=lambda key: candidates[key])
    warn = max(candidates[set_by], np.finfo(float).tiny)
    fault = FAULT_OVER_WARN * warn
    return ChannelThresholds(
        sigma=sigma,
        healthy_peak=peak,
        certified_rms=certified,
        warn=_round_up(warn),
        fault=_round_up(fault),
        smallest_warn_bias=warn + 2.0 * sigma,
        smallest_fault_bias=fault + 2.0 * sigma,
        required_bias=required_bias,
        gust_peak=gust_peak,
        set_by=set_by,
    )


def _running_min(x: FloatArray, window: int) -> FloatArray:
    """min over each run of ``window`` consecutive samples, (K - window + 1,)."""
    if x.size < window:
        return np.zeros(0)
    return np.asarray(np.lib.stride_tricks.sliding_window_view(x, window).min(axis=1))


def jump_size(channel: ChannelThresholds) -> float:
    """The effectiveness stage's bias-step size of a channel (``torque_jump_nm``, ``steer_jump_rad``; docs/math.md
    section 14): half the stated gust's held response (that gust's step at two standard deviations), or 0 (no jump
    test) where that response is within JUMP_NOISE_SIGMAS of the healthy estimate's noise."""
    if channel.gust_peak <= JUMP_NOISE_SIGMAS * channel.sigma:
        return 0.0
    return _round_up(channel.gust_peak / 2.0)


def _round_up(value: float) -> float:
    """To three significant digits, upwards (thresholds read well and never fall below what was computed)."""
    if value <= 0:
        return value
    digits = 3 - math.floor(math.log10(value)) - 1
    factor = 10.0**digits
    return math.ceil(value * factor) / factor


def _hiding(channel: str, t: ChannelThresholds, nominal_torque_nm: float) -> str:
    unit = UNITS[channel]
    what = (
        f"a torque fault of 10 % of the nominal drive torque ({t.required_bias:.4g} {unit} of {nominal_torque_nm:.4g})"
        if channel == "torque"
        else f"a steering fault of {t.required_bias:g} {unit}"
    )
    return (
        f"the {channel} thresholds would hide {what}: FAULT {t.fault:.4g} {unit} needs a bias of about "
        f"{t.smallest_fault_bias:.4g} {unit}. The healthy estimate varies by {t.sigma:.3g} {unit} RMS (largest "
        f"held excursion {t.healthy_peak:.3g}); calibrate from recordings of the vehicle's usual driving, check "
        "the sensors' noise, or accept a higher false-alarm rate (--false-alarms)"
    )


#: What a calibration keeps of a running profile's parameters: what a data sheet states, and the yaw inertia.
BASE_FROM_PROFILE = ("mass_kg", "yaw_inertia_kgm2", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m")


def base_from_profile(spec: ProfileSpec) -> dict[str, Any]:
    """The base of a calibration (``request["base"]`` of :func:`run_calibration`) from a running profile: its
    parameters of BASE_FROM_PROFILE, its design options as they were set, and its alarm settings."""
    return {
        "params": {k: getattr(spec.params, k) for k in BASE_FROM_PROFILE},
        "design": spec.design.model_dump(mode="json", exclude_unset=True),
        "alarms": spec.alarms.model_dump(mode="json"),
    }


def run_calibration(request: dict[str, Any]) -> dict[str, Any]:
    """Worker-process entry point of ``POST /profiles/{name}/calibration``: plain data in and out.

    request : {"base": {"params", "design"?, "alarms"?, "description"?}, "recordings": [{"name", "csv",
    "payload_kg"?}],
    "false_alarms_per_1000_h", "nominal_torque_nm", "gust_n"?, "effectiveness"?}. Returns {"ok": True, "profile",
    "report"} or {"ok": False, "error": "bad_recording" | "refused" | "design_failed" | "bad_request", "reason"}.
    """
    from edge_client.recording import RecordingError, parse_recording
    from synth.calibration import CalibrationRefused
    from synth.errors import SynthesisError

    base = request["base"]
    period = float(base["params"].get("sample_period_s", 0.01))
    drives = []
    for item in request["recordings"]:
        try:
            rec = parse_recording(item["csv"].splitlines(), period, source=item["name"])
        except RecordingError as exc:
            return {"ok": False, "error": "bad_recording", "reason": str(exc)}
        payload = float(item.get("payload_kg", 0.0))
        drives.append(Drive(t=rec.t, y=rec.y, u=rec.u, name=item["name"], grade=rec.grade, payload_kg=payload))
    try:
        report = calibrate_from_base(
            drives,
            base,
            nominal_torque_nm=request.get("nominal_torque_nm"),
            false_alarms_per_1000_h=float(request.get("false_alarms_per_1000_h", 1.0)),
            gust_n=float(request.get("gust_n", GUST_N)),
            effectiveness=bool(request.get("effectiveness", False)),
        )
    except CalibrationRefused as exc:
        return {"ok": False, "error": "refused", "reason": exc.reason}
    except SynthesisError as exc:
        return {"ok": False, "error": "design_failed", "reason": str(exc)}
    except ValueError as exc:
        return {"ok": False, "error": "bad_request", "reason": str(exc)}
    return {"ok": True, "profile": report.profile_document(), "report": _jsonable(report.summary())}


def _jsonable(value: Any) -> Any:
    """numpy scalars and NaN out of a summary: plain JSON (NaN becomes None)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool | str) or value is None:
        return value
    number = float(value)
    return number if math.isfinite(number) else None

"""Grey-box identification of a vehicle profile from healthy recordings (``agv-fe calibrate``).

A vehicle engineer knows the mass, the axle distances, the wheel radius and
usually the yaw inertia; the model also needs what a data sheet does not
give: the effective mass of the longitudinal motion, the drag and rolling
resistance, the cornering stiffnesses, and the noise of the two sensors.
They are identified from recordings of healthy driving (t, v_x, r, T_d,
delta_d at 100 Hz), in three steps, each with a kept scipy routine:

1. **Sensor noise** from the second differences of v_x and r: at 100 Hz the
   signals' own second differences are negligible, white noise of standard
   deviation sigma gives sigma^2 * 6; a median-based estimate ignores the
   rare manoeuvre peaks.
2. **Lateral** (eqs. 1-2 without v_x): C_f, C_r (and I_z when the base does
   not give it) by output error on the yaw rate, scipy.optimize.least_squares.
   v_y is simulated from delta_d and the measured v_x (RK4, inputs held over
   each sample) and the simulated r is compared with the measured one. Only
   the linear range of the tyres is fitted (|a_y| <= ``linear_lateral_accel``,
   0.35 g by default, 0.5 s after a harder corner), so the stiffnesses are
   the tyres' initial slopes. A steering offset is fitted beside them, and a
   large one refuses the recording (a fault or a misaligned sensor).
3. **Longitudinal**: eq. (1) integrated over windows of ``window_s``,

       v_x(t_b) - v_x(t_a) - int v_y r dt
           = (1 / m_eff) int (T_d / R_w - F_yf sin(delta)) dt - (C_x / m_eff) int v_x^2 dt - (F_r / m_eff) (t_b - t_a),

   linear in theta = [1/m_eff, C_x/m_eff, F_r/m_eff] with v_y and F_yf from
   step 2: bounded linear least squares (scipy.optimize.lsq_linear, all
   three non-negative). Integrating instead of differentiating keeps the
   sensor noise out of the regressors; it is left only in the left-hand side.

Every parameter comes with a 95 % confidence interval from the fit's
Jacobian, widened by the residuals' autocorrelation (effective sample size),
and the fit residuals are reported. A parameter the data cannot pin down
is refused with the reason in plain words (:class:`CalibrationRefused`):
too little driving, no acceleration, no cornering, non-finite rows, or a
recording whose residuals look like a fault (a steering offset, a drive-force
deficit in one part of a drive).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.optimize
import scipy.signal

from synth.errors import SynthesisError
from synth.model import FloatArray, grade_torque, lagged_steer, payload_torque
from synth.params import STANDARD_GRAVITY_MPS2, OperatingBounds, VehicleParams

#: Standard gravity [m/s^2].
GRAVITY = 9.81
#: Samples averaged at each end of a longitudinal window (odd): the speed's noise there falls by its square root.
ENDPOINT_SAMPLES = 21
#: What the base profile must give: what a data sheet states.
REQUIRED_BASE_FIELDS = ("mass_kg", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m")
#: What calibration identifies (yaw_inertia_kgm2 too when the base leaves it out).
IDENTIFIED_FIELDS = (
    "steer_time_constant_s",
    "effective_mass_kg",
    "longitudinal_drag_coeff",
    "rolling_resistance_n",
    "front_cornering_stiffness_npr",
    "rear_cornering_stiffness_npr",
)


class CalibrationRefused(SynthesisError):
    """The recordings cannot identify the profile; ``reason`` says why in plain words."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Drive:
    """One recording: t (K,) [s], y (K, 2) measured [v_x [m/s], r [rad/s]], u (K, 2) demanded [T_d [N m],
    delta_d [rad]]; ``name`` for messages; ``grade`` (K,) the road grade the vehicle reported [rad, + uphill], or
    None on level ground; ``leveled``: u's torque is already the level-ground one (:func:`level_ground`);
    ``payload_kg`` the load the vehicle carried through the recording, beyond the profile's vehicle [kg]."""

    t: FloatArray
    y: FloatArray
    u: FloatArray
    name: str = "recording"
    grade: FloatArray | None = None
    leveled: bool = False
    payload_kg: float = 0.0

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class CalibrationOptions:
    """How strict calibration is; the defaults suit a road vehicle sampled at 100 Hz."""

    #: samples below this speed are not fitted (the tyre model of eq. 2 divides by v_x) [m/s]
    min_speed_mps: float = 5.0
    #: at least this much driving above min_speed_mps in all [s]
    min_duration_s: float = 30.0
    #: the tyres' linear range: the lateral fit uses |a_y| below this [m/s^2]
    linear_lateral_accel_mps2: float = 0.35 * GRAVITY
    #: window of the longitudinal fit [s]
    window_s: float = 1.0
    #: the longitudinal fit needs this many windows with |mean a_x| above accel_threshold
    min_accel_windows: int = 8
    accel_threshold_mps2: float = 0.5
    #: the lateral fit needs this long with |a_y| above cornering_threshold
    min_cornering_s: float = 5.0
    cornering_threshold_mps2: float = 1.5
    #: largest relative 95 % half-width accepted for each identified parameter. The torque channel needs the
    #: effective mass to a few per cent (2.5 % of mass error reads as 2.5 % of the drive force); the steering
    #: channel is forgiving, and the thresholds are set from the observer's residuals with the identified
    #: stiffnesses, so a looser stiffness costs sensitivity, not false alarms
    max_relative_ci: dict[str, float] = field(
        default_factory=lambda: {
            "effective_mass_kg": 0.02,
            "front_cornering_stiffness_npr": 0.25,
            "rear_cornering_stiffness_npr": 0.25,
            "yaw_inertia_kgm2": 0.25,
        }
    )
    #: a steering offset beyond this refuses the recordings (a fault or a misaligned sensor) [rad]
    max_steer_offset_rad: float = 0.008
    #: a block of the longitudinal residual off by more than this, and 4 standard errors, looks faulty [m/s^2]
    fault_accel_floor_mps2: float = 0.12
    #: ... and of the yaw-rate residual [rad/s]
    fault_yaw_rate_floor_radps: float = 0.02
    #: length of the blocks the fault test compares [s]
    fault_block_s: float = 10.0


@dataclass(frozen=True)
class Estimate:
    """An identified parameter: value, 95 % confidence interval, and whether it came from the data."""

    value: float
    low: float
    high: float
    identified: bool = True

    @property
    def relative_half_width(self) -> float:
        return 0.5 * (self.high - self.low) / abs(self.value) if self.value else math.inf


@dataclass(frozen=True)
class CalibrationResult:
    """What calibration found.

    params : the complete vehicle parameters (base + identified, cornering drag on)
    bounds : an operating box that holds the recordings, with margins (see :func:`operating_bounds`)
    estimates : every identified parameter with its confidence interval
    noise : sensor sigma per channel {"vx_sigma_mps", "r_sigma_radps"}
    residuals : fit quality: RMS of the yaw-rate output error, of the longitudinal window residual, and
        their ratio to what the sensor noise alone explains
    steer_offset_rad : the fitted steering offset (reported, not used)
    duration_s : driving time used
    """

    params: VehicleParams
    bounds: OperatingBounds
    estimates: dict[str, Estimate]
    noise: dict[str, float]
    residuals: dict[str, float]
    steer_offset_rad: float
    duration_s: float
    peak_lateral_accel_mps2: float
    notes: list[str] = field(default_factory=list)


def level_ground(drive: Drive, base: dict[str, Any]) -> Drive:
    """``drive`` as the profile's vehicle would have driven it on level ground: the torque T_d less the grade's
    R_w M_v g sin(theta) (synth.model.grade_torque, docs/math.md 12.6), which is what the service gives the model
    for a measurement that carries the grade; the grade is kept (the load the tyres' force moves between the axles
    follows the torque, not the acceleration the grade slows). A drive without a grade, one leveled already, or
    one with a payload (calibration takes its grade with the payload, :func:`_fit_with_payloads`) is returned as
    it is."""
    if drive.grade is None or drive.leveled:
        return drive
    _check_grade(drive, base)
    if drive.payload_kg > 0.0:
        return drive
    vehicle = VehicleParams(mass_kg=base["mass_kg"], wheel_radius_m=base["wheel_radius_m"])
    u = drive.u.astype(float).copy()
    u[:, 0] -= grade_torque(drive.grade, 0.0, vehicle)
    return Drive(t=drive.t, y=drive.y, u=u, name=drive.name, grade=drive.grade, leveled=True)


def _check_grade(drive: Drive, base: dict[str, Any]) -> None:
    """Refuse a drive whose grade is not finite, not one per sample, or without the base's mass and wheel radius."""
    assert drive.grade is not None
    bad = np.flatnonzero(~np.isfinite(drive.grade))
    if bad.size:
        raise CalibrationRefused(f"{drive.name}: row {int(bad[0]) + 1} has a non-finite grade")
    if drive.grade.shape != drive.t.shape:
        raise CalibrationRefused(f"{drive.name}: {drive.grade.size} grades for {drive.t.size} samples")
    missing = [name for name in ("mass_kg", "wheel_radius_m") if name not in base]
    if missing:
        raise CalibrationRefused(f"a recording with a road grade needs {' and '.join(missing)} in the base profile")


def calibrate(
    drives: Sequence[Drive], base: dict[str, Any], options: CalibrationOptions | None = None
) -> CalibrationResult:
    """Identify a vehicle profile from healthy drives.

    What ``base`` gives is kept; what it leaves out of :data:`IDENTIFIED_FIELDS` (and the yaw inertia) is
    identified.

    Parameters
    ----------
    drives : sequence of Drive
        The healthy recordings (100 Hz); one with a road grade is taken on level ground (:func:`level_ground`),
        one with a payload to the vehicle without it (:func:`_fit_with_payloads`).
    base : dict
        Vehicle parameters by their field names (synth.params.VehicleParams).
    options : CalibrationOptions, optional
        Windows, thresholds and limits of the identification (defaults if None).

    Returns
    -------
    CalibrationResult
        The parameters, their confidence intervals, the sensor noise, the fit's residuals and an operating box.

    Raises
    ------
    CalibrationRefused
        The recordings cannot identify the profile; the message says why (no acceleration, too little
        turning, a non-finite value, an interval too wide...).
    """
    options = options or CalibrationOptions()
    _check_inputs(drives, base)
    drives = [level_ground(d, base) for d in drives]
    sample_period_s = float(base.get("sample_period_s", VehicleParams().sample_period_s))
    prepared = [_prepare(d, sample_period_s, options) for d in drives]
    duration_s = sum(float(np.count_nonzero(p.moving)) for p in prepared) * sample_period_s
    if duration_s < options.min_duration_s:
        raise CalibrationRefused(
            f"too short: {duration_s:.1f} s of driving above {options.min_speed_mps:g} m/s in all, "
            f"calibration needs at least {options.min_duration_s:g} s"
        )
    noise = _sensor_noise(prepared)
    fixed = VehicleParams.model_validate({**base, "cornering_drag": True})
    lateral = _fit_lateral(prepared, fixed, "yaw_inertia_kgm2" not in base, noise, options)
    _check_load_transfer(prepared, fixed, lateral, noise, options)
    params_lat = fixed.model_copy(update=lateral.params)
    sims = [_simulate_lateral(p, params_lat, lateral.steer_offset) for p in prepared]
    prepared, longitudinal = _fit_with_payloads(drives, prepared, sims, params_lat, base, noise, options)
    params = params_lat.model_copy(update=longitudinal.params)
    params = VehicleParams.model_validate(params.model_dump())  # re-validated as a whole
    _check_fault_blocks(prepared, sims, longitudinal, lateral, params, options)
    estimates = {**lateral.estimates, **longitudinal.estimates}
    for name, limit in options.max_relative_ci.items():
        est = estimates.get(name)
        if est is not None and est.identified and est.relative_half_width > limit:
            raise CalibrationRefused(_unidentified(name, est, limit, params))
    residuals = {**lateral.residuals, **longitudinal.residuals}
    bounds = operating_bounds(prepared, sims, params, lateral.steer_offset)
    peak_ay = max(float(np.max(np.abs(p.v_x * p.r), initial=0.0)) for p in prepared)
    notes = _notes(drives, params, options, peak_ay)
    return CalibrationResult(
        params=params,
        bounds=bounds,
        estimates=estimates,
        noise=noise,
        residuals=residuals,
        steer_offset_rad=lateral.steer_offset,
        duration_s=duration_s,
        peak_lateral_accel_mps2=peak_ay,
        notes=notes,
    )


def _notes(drives: Sequence[Drive], params: VehicleParams, options: CalibrationOptions, peak_ay: float) -> list[str]:
    """What the report says beside the figures: the stiffnesses' range, the payloads left out, a missing CG height."""
    notes = [
        f"cornering stiffnesses fitted where |a_y| <= {options.linear_lateral_accel_mps2:.2f} m/s^2 "
        f"(the tyres' linear range); the recordings reach {peak_ay:.1f} m/s^2",
    ]
    carried = [f"{d.name} {d.payload_kg:g} kg" for d in drives if d.payload_kg > 0.0]
    if carried:
        notes.append(f"identified without the payloads the recordings carried ({', '.join(carried)})")
    if params.cg_height_m == 0.0:
        notes.append(
            "no centre-of-gravity height (cg_height_m) in the base: the model leaves out the load that braking and "
            "accelerating move between the axles, so braking hard in a turn reads as a steering fault "
            "(docs/math.md 12.4); give the data sheet's height"
        )
    return notes


# ---------------------------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class _Prepared:
    """A drive ready for the fits: the measured signals, a lightly smoothed v_x, and masks."""

    name: str
    t: FloatArray
    v_x: FloatArray  # smoothed, floored at 1 m/s
    v_x_raw: FloatArray
    r: FloatArray
    accel: FloatArray  # dv_x/dt, the same fit's derivative, + g sin(theta) on a grade: what moves load
    torque: FloatArray
    steer: FloatArray
    moving: np.ndarray  # v_x above min_speed
    linear: np.ndarray  # moving, in the tyres' linear range, settled after a harder corner
    s: float


def _check_inputs(drives: Sequence[Drive], base: dict[str, Any]) -> None:
    if not drives:
        raise CalibrationRefused("no recordings given")
    missing = [name for name in REQUIRED_BASE_FIELDS if name not in base]
    if missing:
        raise CalibrationRefused(
            f"the base profile must give {', '.join(missing)}: what a data sheet states is kept, not identified"
        )
    for drive in drives:
        for label, values in (("t", drive.t), ("y", drive.y), ("u", drive.u)):
            bad = np.flatnonzero(~np.all(np.isfinite(np.atleast_2d(values.T).T), axis=-1))
            if bad.size:
                raise CalibrationRefused(f"{drive.name}: row {int(bad[0]) + 1} has a non-finite {label} value")
        if len(drive) < 2:
            raise CalibrationRefused(f"{drive.name}: fewer than 2 samples")
        if not (math.isfinite(drive.payload_kg) and 0.0 <= drive.payload_kg <= float(base["mass_kg"])):
            raise CalibrationRefused(
                f"{drive.name}: a payload must be finite, 0 kg or more and at most the vehicle's mass_kg "
                f"({float(base['mass_kg']):g} kg), got {drive.payload_kg:g} kg"
            )


def _prepare(drive: Drive, s: float, options: CalibrationOptions) -> _Prepared:
    v_raw = drive.y[:, 0].astype(float)
    # a quadratic Savitzky-Golay over 0.21 s: the speed for 1/v_x and v_x^2 without its sensor noise
    window = min(21, v_raw.size - (1 - v_raw.size % 2))
    v_x = scipy.signal.savgol_filter(v_raw, window, 2) if window >= 5 else v_raw.copy()
    v_x = np.maximum(v_x, 1.0)
    # dv_x/dt of the same fit, and on a grade g sin(theta) more: the acceleration the tyres' force on the road
    # gives, m (a_x + g sin(theta)), which moves load between the axles (the weight's pull acts at the centre of
    # gravity and moves none)
    accel = scipy.signal.savgol_filter(v_raw, window, 2, deriv=1, delta=s) if window >= 5 else np.gradient(v_raw, s)
    if drive.grade is not None:
        accel = accel + STANDARD_GRAVITY_MPS2 * np.sin(drive.grade)
    r = drive.y[:, 1].astype(float)
    moving = v_x >= options.min_speed_mps
    hard = np.abs(v_x * scipy.signal.savgol_filter(r, window, 2) if window >= 5 else v_x * r)
    hard = hard > options.linear_lateral_accel_mps2
    # 0.5 s after a harder corner the lateral transient has settled
    settle = max(1, round(0.5 / s))
    recent_hard = np.convolve(hard.astype(float), np.ones(settle), mode="full")[: hard.size] > 0
    linear = moving & ~recent_hard
    linear[: round(1.0 / s)] = False  # the simulated v_y starts from a guess
    return _Prepared(
        name=drive.name,
        t=drive.t.astype(float),
        v_x=v_x,
        v_x_raw=v_raw,
        r=r,
        accel=np.asarray(accel, dtype=float),
        torque=drive.u[:, 0].astype(float),
        steer=drive.u[:, 1].astype(float),
        moving=moving,
        linear=linear,
        s=s,
    )


def _sensor_noise(prepared: Sequence[_Prepared]) -> dict[str, float]:
    """sigma of white sensor noise from second differences: Var(Delta^2 n) = 6 sigma^2; median-based."""

    def sigma(signals: list[FloatArray]) -> float:
        second = np.concatenate([np.diff(x, 2) for x in signals if x.size > 2])
        mad = float(np.median(np.abs(second - np.median(second))))
        return 1.4826 * mad / math.sqrt(6.0)

    vx = sigma([p.v_x_raw[p.moving] for p in prepared])
    r = sigma([p.r[p.moving] for p in prepared])
    if not (vx > 0 and r > 0):
        raise CalibrationRefused(
            "the recordings have no sensor noise at all (constant or quantised signals): cannot size the "
            "observer's noise model; record the raw sensor values"
        )
    return {"vx_sigma_mps": vx, "r_sigma_radps": r}


# ---------------------------------------------------------------------------------------------- lateral


@dataclass(frozen=True)
class _LateralFit:
    params: dict[str, float]
    estimates: dict[str, Estimate]
    steer_offset: float
    residuals: dict[str, float]
    rms_r: float


def _simulate_lateral(
    p: _Prepared,
    params: VehicleParams,
    steer_offset: float,
    C_f: float | None = None,
    C_r: float | None = None,
    I_z: float | None = None,
    tau: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(v_y, r, delta) of eqs. (1)-(2) driven by the measured v_x and the road-wheel angle delta: delta_d + offset
    (+ the load transfer's angle, with a centre-of-gravity height) through the steering actuator's lag
    (synth.model.lagged_steer), RK4 with the inputs held over each sample.

    v_y starts at 0 and r at the measured value; the first second is not fitted.
    """
    k = params.symbols()
    C_f = k["C_f"] if C_f is None else C_f
    C_r = k["C_r"] if C_r is None else C_r
    I_z = k["I_z"] if I_z is None else I_z
    tau = params.steer_time_constant_s if tau is None else tau
    m, l_f, l_r, C_y = k["M_v"], k["l_f"], k["l_r"], k["C_y"]
    s = p.s
    v_x = p.v_x.tolist()
    lag = params.model_copy(update={"steer_time_constant_s": tau})
    delta = lagged_steer(p.steer + steer_offset + _load_transfer_steer(p, params, C_f, C_r), lag)
    steer = delta.tolist()
    n = len(v_x)
    vy_out = [0.0] * n
    r_out = [0.0] * n
    vy, r = 0.0, float(p.r[0])
    a, b = 2.0 * C_f, 2.0 * C_r

    def deriv(vy: float, r: float, vx: float, d: float) -> tuple[float, float]:
        F_f = a * (d - (vy + l_f * r) / vx)
        F_r = b * (l_r * r - vy) / vx
        return (F_f + F_r - C_y * vy * vy) / m - vx * r, (l_f * F_f - l_r * F_r) / I_z

    h = 0.5 * s
    for i in range(n):
        vy_out[i], r_out[i] = vy, r
        vx, d = v_x[i], steer[i]
        k1 = deriv(vy, r, vx, d)
        k2 = deriv(vy + h * k1[0], r + h * k1[1], vx, d)
        k3 = deriv(vy + h * k2[0], r + h * k2[1], vx, d)
        k4 = deriv(vy + s * k3[0], r + s * k3[1], vx, d)
        vy += s / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        r += s / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    return np.array(vy_out), np.array(r_out), delta


def _load_transfer_steer(p: _Prepared, params: VehicleParams, C_f: float, C_r: float) -> FloatArray | float:
    """The load transfer's steering angle (synth.model.load_transfer_steer_rad) over a recording, with the
    stiffnesses being fitted and the measured acceleration (the effective mass is not known yet); 0 without a
    centre-of-gravity height."""
    if params.cg_height_m == 0.0:
        return 0.0
    gain = params.model_copy(
        update={"front_cornering_stiffness_npr": C_f, "rear_cornering_stiffness_npr": C_r}
    ).load_transfer_gain
    return -gain * p.accel * (p.v_x * p.r)


def _check_load_transfer(
    prepared: Sequence[_Prepared],
    params: VehicleParams,
    lateral: _LateralFit,
    noise: dict[str, float],
    options: CalibrationOptions,
) -> None:
    """With a centre-of-gravity height, a lateral fit that cannot identify the stiffnesses is fitted again
    without the load transfer: if that one identifies them, the recordings do not show the load transfer the
    stated height predicts (the fit, whose gain G follows the stiffnesses, traded stiffness for the term), and
    the refusal says so rather than asking for more turns (docs/math.md 12.4)."""
    if params.cg_height_m == 0.0:
        return
    names = ("front_cornering_stiffness_npr", "rear_cornering_stiffness_npr")
    limits = {name: options.max_relative_ci.get(name, math.inf) for name in names}
    if all(lateral.estimates[name].relative_half_width <= limits[name] for name in names):
        return
    plain = _fit_lateral(
        prepared,
        params.model_copy(update={"cg_height_m": 0.0}),
        "yaw_inertia_kgm2" in lateral.params,
        noise,
        options,
    )
    if any(plain.estimates[name].relative_half_width > limits[name] for name in names):
        return  # not identifiable either way: the general refusal says what to record
    with_h, without = lateral.estimates[names[0]], plain.estimates[names[0]]
    raise CalibrationRefused(
        f"the recordings do not show the load transfer that cg_height_m = {params.cg_height_m:g} m predicts: "
        f"with it the front cornering stiffness is {with_h.value:.4g} N/rad "
        f"(+-{100 * with_h.relative_half_width:.0f} %), without it {without.value:.4g} N/rad "
        f"(+-{100 * without.relative_half_width:.0f} %). Check the height against the data sheet, or leave "
        "cg_height_m out of the base to calibrate without the term"
    )


def _fit_lateral(
    prepared: Sequence[_Prepared],
    params: VehicleParams,
    fit_yaw_inertia: bool,
    noise: dict[str, float],
    options: CalibrationOptions,
) -> _LateralFit:
    """Output error on r over the linear-range samples: log C_f, log C_r (, log I_z) and a steering offset."""
    cornering_s = sum(
        float(np.count_nonzero(p.moving & (np.abs(p.v_x * p.r) >= options.cornering_threshold_mps2))) * p.s
        for p in prepared
    )
    if cornering_s < options.min_cornering_s:
        raise CalibrationRefused(
            f"no cornering: only {cornering_s:.1f} s with a lateral acceleration above "
            f"{options.cornering_threshold_mps2:g} m/s^2 (at least {options.min_cornering_s:g} s needed to "
            "identify the cornering stiffnesses); record turns, lane changes or a slalom"
        )
    linear_s = sum(float(np.count_nonzero(p.linear)) * p.s for p in prepared)
    if linear_s < options.min_duration_s:
        raise CalibrationRefused(
            f"too little driving in the tyres' linear range: {linear_s:.1f} s with |a_y| below "
            f"{options.linear_lateral_accel_mps2:.2f} m/s^2, at least {options.min_duration_s:g} s needed"
        )
    k = params.symbols()
    # start from a typical tyre: cornering stiffness ~ 16 x its static load per radian
    L = k["l_f"] + k["l_r"]
    load_f = 0.5 * k["M_v"] * GRAVITY * k["l_r"] / L
    load_r = 0.5 * k["M_v"] * GRAVITY * k["l_f"] / L
    # theta = [log C_f, log C_r, offset [mrad], tau [10 ms] (, log I_z)]
    x0 = [math.log(16.0 * load_f), math.log(16.0 * load_r), 0.0, 5.0]
    lower = [-np.inf, -np.inf, -np.inf, 0.0]
    upper = [np.inf, np.inf, np.inf, 50.0]
    if fit_yaw_inertia:
        x0.append(math.log(k["M_v"] * k["l_f"] * k["l_r"]))
        lower.append(-np.inf)
        upper.append(np.inf)
    scale_r = noise["r_sigma_radps"]

    def residual(theta: FloatArray) -> FloatArray:
        C_f, C_r, offset, tau = math.exp(theta[0]), math.exp(theta[1]), 1e-3 * theta[2], 0.01 * theta[3]
        I_z = math.exp(theta[4]) if fit_yaw_inertia else None
        parts = []
        for p in prepared:
            _, r_sim, _ = _simulate_lateral(p, params, offset, C_f, C_r, I_z, tau)
            parts.append((r_sim - p.r)[p.linear] / scale_r)
        return np.concatenate(parts)

    fit = scipy.optimize.least_squares(
        residual, np.array(x0), bounds=(lower, upper), method="trf", x_scale=1.0, diff_step=1e-4
    )
    theta = fit.x
    res = fit.fun
    cov = _covariance(fit.jac, res, _autocorrelation_factor(res))
    names = ["front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"]
    estimates = {name: _log_estimate(theta[i], cov[i, i]) for i, name in enumerate(names)}
    values = {name: estimates[name].value for name in names}
    tau, tau_sd = 0.01 * float(theta[3]), 0.01 * math.sqrt(max(cov[3, 3], 0.0))
    estimates["steer_time_constant_s"] = Estimate(tau, max(0.0, tau - 1.96 * tau_sd), tau + 1.96 * tau_sd)
    values["steer_time_constant_s"] = tau
    if fit_yaw_inertia:
        estimates["yaw_inertia_kgm2"] = _log_estimate(theta[4], cov[4, 4])
        values["yaw_inertia_kgm2"] = estimates["yaw_inertia_kgm2"].value
    offset = 1e-3 * float(theta[2])
    offset_ci = 1e-3 * 1.96 * math.sqrt(max(cov[2, 2], 0.0))
    if abs(offset) > options.max_steer_offset_rad:
        raise CalibrationRefused(
            f"the steering looks biased: the vehicle turns as if the road-wheel angle were {offset:+.4f} rad "
            f"(+-{offset_ci:.4f}) off the demand. That is a steering fault or a misaligned angle sensor; "
            "calibrate from a healthy drive with a calibrated steering-angle signal"
        )
    rms_r = float(np.sqrt(np.mean(res**2))) * scale_r
    return _LateralFit(
        params=values,
        estimates=estimates,
        steer_offset=offset,
        residuals={"yaw_rate_rms_radps": rms_r, "yaw_rate_rms_over_noise": rms_r / scale_r},
        rms_r=rms_r,
    )


# ------------------------------------------------------------------------------------------ longitudinal


@dataclass(frozen=True)
class _LongitudinalFit:
    params: dict[str, float]
    estimates: dict[str, Estimate]
    residuals: dict[str, float]
    theta: FloatArray
    window_samples: int


def _windows(p: _Prepared, n: int) -> list[tuple[int, int]]:
    """Non-overlapping windows of n samples within runs of moving samples: (start, end) index pairs."""
    out: list[tuple[int, int]] = []
    start = 0
    while start + n < p.t.size:
        end = start + n
        if p.moving[start : end + 1].all():
            out.append((start, end))
        start = end
    return out


def _longitudinal_rows(
    p: _Prepared, vy: FloatArray, delta: FloatArray, params: VehicleParams, n: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """For each window: the regressors [int (T/R_w - F_yf sin delta), -int v_x^2, -(t_b - t_a)], the left-hand
    side v_x(t_b) - v_x(t_a) - int v_y r, the window's mean |a_y| and its start time."""
    k = params.symbols()
    s = p.s
    F_yf = 2.0 * k["C_f"] * (delta - (vy + k["l_f"] * p.r) / p.v_x)
    drive = p.torque / k["R_w"] - F_yf * np.sin(delta)

    # trapezoid integrals as differences of cumulative sums
    def cumulative(x: FloatArray) -> FloatArray:
        return np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * s)])

    # the inputs are held over each sample, so their integral is a left Riemann sum
    def held(x: FloatArray) -> FloatArray:
        return np.concatenate([[0.0], np.cumsum(x[:-1] * s)])

    # the same centred moving average on both sides of v(b) - v(a) = I(b) - I(a) keeps it exact and averages
    # the speed sensor's noise at the window ends over ENDPOINT_SAMPLES samples
    def smooth(x: FloatArray) -> FloatArray:
        return np.convolve(x, np.full(ENDPOINT_SAMPLES, 1.0 / ENDPOINT_SAMPLES), mode="same")

    I_drive, I_v2, I_vyr = (smooth(x) for x in (held(drive), cumulative(p.v_x**2), cumulative(vy * p.r)))
    v_ends = smooth(p.v_x_raw)
    half = ENDPOINT_SAMPLES // 2
    windows = [(i, j) for i, j in _windows(p, n) if i >= half and j < p.t.size - half]
    if not windows:
        empty = np.zeros((0,))
        return np.zeros((0, 3)), empty, empty, empty
    a = np.array([w[0] for w in windows])
    b = np.array([w[1] for w in windows])
    X = np.column_stack([I_drive[b] - I_drive[a], -(I_v2[b] - I_v2[a]), -(p.t[b] - p.t[a])])
    rhs = v_ends[b] - v_ends[a] - (I_vyr[b] - I_vyr[a])
    ay = np.array([float(np.mean(np.abs(p.v_x[i:j] * p.r[i:j]))) for i, j in windows])
    return X, rhs, ay, p.t[a]


def _ratio_estimates(
    names: Sequence[str], theta: FloatArray, cov: FloatArray, inv_m: float, m_free: bool
) -> dict[str, Estimate]:
    """The physical values of the fitted theta = [1/m_eff, C_x/m_eff, F_r/m_eff] (its free entries, named by
    ``names``, "inv_m" for 1/m_eff) with 95 % intervals: each is a ratio to 1/m_eff, its variance by the delta
    method from theta's covariance ``cov``. inv_m : float  [1/kg], fitted or given."""
    estimates: dict[str, Estimate] = {}
    for i, name in enumerate(names):
        grad = np.zeros(len(names))
        if name == "inv_m":
            value = 1.0 / inv_m
            grad[i] = -1.0 / inv_m**2
            name = "effective_mass_kg"
        elif m_free:
            value = theta[i] / inv_m
            grad[i], grad[0] = 1.0 / inv_m, -theta[i] / inv_m**2
        else:
            value = theta[i] / inv_m
            grad[i] = 1.0 / inv_m
        sd = math.sqrt(max(float(grad @ cov @ grad), 0.0))
        low = value - 1.96 * sd if name == "effective_mass_kg" else max(0.0, value - 1.96 * sd)
        estimates[name] = Estimate(value, low, value + 1.96 * sd)
    return estimates


def _fit_longitudinal(
    prepared: Sequence[_Prepared],
    sims: Sequence[tuple[FloatArray, FloatArray, FloatArray]],
    params: VehicleParams,
    base: dict[str, Any],
    noise: dict[str, float],
    options: CalibrationOptions,
) -> _LongitudinalFit:
    s = prepared[0].s
    n = max(2, round(options.window_s / s))
    rows = [_longitudinal_rows(p, sim[0], sim[2], params, n) for p, sim in zip(prepared, sims, strict=True)]
    X = np.vstack([row[0] for row in rows])
    rhs = np.concatenate([row[1] for row in rows])
    ay = np.concatenate([row[2] for row in rows])
    keep = ay <= options.linear_lateral_accel_mps2
    X, rhs = X[keep], rhs[keep]
    accel = np.abs(rhs) / (n * s)
    if int(np.count_nonzero(accel >= options.accel_threshold_mps2)) < options.min_accel_windows:
        raise CalibrationRefused(
            f"no acceleration: only {int(np.count_nonzero(accel >= options.accel_threshold_mps2))} windows of "
            f"{n * s:g} s with a mean acceleration or braking above {options.accel_threshold_mps2:g} m/s^2 "
            f"(at least {options.min_accel_windows} needed to identify the effective mass); record speed changes"
        )
    # rhs = (1 / m_eff) (X_0 + C_x X_1 + F_r X_2): what the base gives is folded in, the rest is fitted as
    # theta = [1/m_eff, C_x/m_eff, F_r/m_eff] (those free), in scales near one for the bounded solver
    given = {
        name: float(base[name])
        for name in ("effective_mass_kg", "longitudinal_drag_coeff", "rolling_resistance_n")
        if name in base
    }
    col0 = X[:, 0].copy()
    if "longitudinal_drag_coeff" in given:
        col0 += given["longitudinal_drag_coeff"] * X[:, 1]
    if "rolling_resistance_n" in given:
        col0 += given["rolling_resistance_n"] * X[:, 2]
    m_free = "effective_mass_kg" not in given
    m0 = given.get("effective_mass_kg", 1.05 * params.mass_kg)
    columns, scales, names = [], [], []
    if m_free:
        columns.append(col0)
        scales.append(1.0 / m0)
        names.append("inv_m")
    else:
        rhs = rhs - col0 / m0
    for j, name, unit in ((1, "longitudinal_drag_coeff", 1.0), (2, "rolling_resistance_n", 100.0)):
        if name not in given:
            columns.append(X[:, j])
            scales.append(unit / m0)
            names.append(name)
    values: dict[str, float] = {str(k): v for k, v in given.items()}
    estimates: dict[str, Estimate] = {}
    residual = rhs
    if columns:
        A = np.column_stack(columns) * np.array(scales)
        fit = scipy.optimize.lsq_linear(A, rhs, bounds=(0.0, np.inf))
        residual = rhs - A @ fit.x
        theta = fit.x * np.array(scales)
        cov = _covariance(A, residual, _autocorrelation_factor(residual)) * np.outer(scales, scales)
        inv_m = theta[0] if m_free else 1.0 / m0
        if m_free and inv_m <= 0:
            raise CalibrationRefused(
                "the drive torque does not explain the accelerations: check the torque signal's sign and unit"
            )
        estimates = _ratio_estimates(names, theta, cov, inv_m, m_free)
        values.update({name: e.value for name, e in estimates.items()})
    inv_m = 1.0 / values["effective_mass_kg"]
    theta_full = np.array([inv_m, values["longitudinal_drag_coeff"] * inv_m, values["rolling_resistance_n"] * inv_m])
    window_noise = math.sqrt(2.0 / ENDPOINT_SAMPLES) * noise["vx_sigma_mps"]
    rms = float(np.sqrt(np.mean(residual**2)))
    return _LongitudinalFit(
        params=values,
        estimates=estimates,
        residuals={
            "speed_change_rms_mps": rms,
            "speed_change_rms_over_noise": rms / window_noise,
            "longitudinal_windows": float(residual.size),
        },
        theta=theta_full,
        window_samples=n,
    )


#: The payloads' fixed point (:func:`_fit_with_payloads`) ends when no longitudinal parameter moves by more than
#: this share of itself in a pass (of 1e-3 for the drag coefficient and 1 N for the rolling resistance near zero).
PAYLOAD_FIT_TOLERANCE = 1e-9
#: ... or refuses after this many passes (each moves the effective mass's error by payload / (m_eff + payload)
#: of it, about 0.5 for a payload of the vehicle's mass: some 30 passes then)
PAYLOAD_FIT_PASSES = 60


def _fit_with_payloads(
    drives: Sequence[Drive],
    prepared: Sequence[_Prepared],
    sims: Sequence[tuple[FloatArray, FloatArray, FloatArray]],
    params: VehicleParams,
    base: dict[str, Any],
    noise: dict[str, float],
    options: CalibrationOptions,
) -> tuple[list[_Prepared], _LongitudinalFit]:
    """The longitudinal fit, each drive that carried a payload taken to the profile's vehicle (the vehicle
    without it); returns the drives as fitted and the fit.

    A loaded drive is fitted on the torque the vehicle without the payload needs to move as the loaded one moved,
    on level ground: :func:`synth.model.payload_torque` with the drive's grade, the torque the service gives the
    model once the payload is reported (docs/math.md 12.5, 12.6). That torque depends on what is being fitted
    (rho = m_eff / (m_eff + payload), C_x and F_r), so the torque and the fit are iterated to their fixed point,
    from the base's values (1.05 M_v, 0 and 0 where it gives none): a pass moves the effective mass's error by
    payload / (m_eff + payload) of it, C_x's and F_r's by 1 - rho, a contraction for any payload. The lateral fit
    needs no payload: the tyres' cornering stiffnesses grow with the load they carry, so a load at the centre of
    gravity leaves the lateral accelerations, per kilogram, as they were (docs/math.md 12.5).
    """
    if not any(d.payload_kg > 0.0 for d in drives):
        return list(prepared), _fit_longitudinal(prepared, sims, params, base, noise, options)
    names = ("effective_mass_kg", "longitudinal_drag_coeff", "rolling_resistance_n")
    floors = (1.0, 1e-3, 1.0)
    values = [float(base.get(names[0], 1.05 * params.mass_kg)), float(base.get(names[1], 0.0))]
    values.append(float(base.get(names[2], 0.0)))
    for _ in range(PAYLOAD_FIT_PASSES):
        vehicle = params.model_copy(update=dict(zip(names, values, strict=True)))
        fitted = [_without_payload(p, d, vehicle) for p, d in zip(prepared, drives, strict=True)]
        fit = _fit_longitudinal(fitted, sims, params, base, noise, options)
        new = [float(fit.params[name]) for name in names]
        moved = max(abs(a - b) / max(abs(b), f) for a, b, f in zip(new, values, floors, strict=True))
        values = new
        if moved <= PAYLOAD_FIT_TOLERANCE:
            return fitted, fit
    raise CalibrationRefused(
        f"the fit with the recordings' payloads did not settle in {PAYLOAD_FIT_PASSES} passes (a longitudinal "
        f"parameter moved {moved:.1e} of itself in the last): check the payloads stated for the recordings"
    )


def _without_payload(p: _Prepared, drive: Drive, vehicle: VehicleParams) -> _Prepared:
    """``p`` with the torque ``vehicle`` (without the drive's payload) needs on level ground to move as the loaded
    vehicle moved on the drive's grade; ``p`` itself for a drive without a payload."""
    if drive.payload_kg <= 0.0:
        return p
    grade = 0.0 if drive.grade is None else drive.grade
    torque, _ = payload_torque(p.v_x_raw, drive.u[:, 0], drive.payload_kg, vehicle, grade)
    return replace(p, torque=torque)


# -------------------------------------------------------------------------------------------- checks


def _check_fault_blocks(
    prepared: Sequence[_Prepared],
    sims: Sequence[tuple[FloatArray, FloatArray, FloatArray]],
    longitudinal: _LongitudinalFit,
    lateral: _LateralFit,
    params: VehicleParams,
    options: CalibrationOptions,
) -> None:
    """Refuse a recording whose residuals shift in one block of time: a fault that began mid-drive."""
    n = longitudinal.window_samples
    per_block = max(2, round(options.fault_block_s / (n * prepared[0].s)))
    for p, (vy, r_sim, delta) in zip(prepared, sims, strict=True):
        X, rhs, ay, starts = _longitudinal_rows(p, vy, delta, params, n)
        keep = ay <= options.linear_lateral_accel_mps2
        residual = (rhs - X @ longitudinal.theta)[keep] / (n * p.s)  # mean acceleration error per window
        starts = starts[keep]
        spread = float(np.std(residual)) if residual.size > 1 else 0.0
        for b in range(0, residual.size - per_block + 1, per_block):
            block = residual[b : b + per_block]
            se = spread / math.sqrt(block.size)
            mean = float(np.mean(block))
            if abs(mean) > max(4.0 * se, options.fault_accel_floor_mps2):
                force = mean * params.effective_mass_kg
                until = starts[b + block.size - 1] + n * p.s
                raise CalibrationRefused(
                    f"{p.name} looks faulty: from t = {starts[b]:.1f} s to {until:.1f} s the vehicle accelerates "
                    f"{mean:+.2f} m/s^2 ({force:+.0f} N) unlike the rest of the drive for the same torque: a torque "
                    "fault, a slope or a different load. Calibrate from healthy drives, with the road's grade (a "
                    "grade column) and the load each carried (payload_kg) where they vary"
                )
        r_res = (r_sim - p.r)[p.linear]
        m = max(2, round(options.fault_block_s / p.s))
        spread_r = float(np.std(r_res)) if r_res.size > 1 else 0.0
        for b in range(0, r_res.size - m + 1, m):
            block = r_res[b : b + m]
            mean = float(np.mean(block))
            # consecutive samples are correlated: a tenth of them count as independent
            se = spread_r / math.sqrt(max(block.size / 10.0, 1.0))
            if abs(mean) > max(4.0 * se, options.fault_yaw_rate_floor_radps):
                raise CalibrationRefused(
                    f"{p.name} looks faulty: for {m * p.s:.0f} s the yaw rate is {mean:+.3f} rad/s off what the "
                    "steering demand explains: a steering fault or a different vehicle. Calibrate from healthy drives"
                )


def operating_bounds(
    prepared: Sequence[_Prepared],
    sims: Sequence[tuple[FloatArray, FloatArray, FloatArray]],
    params: VehicleParams,
    offset: float,
) -> OperatingBounds:
    """The design box of a calibrated vehicle.

    The paper's box (eq. 13: 5 to 30 m/s, |r| <= 0.55 rad/s) widened to hold the recorded speeds and yaw rates
    with margins, symmetric in r and delta (the mirror symmetry halves the LMIs); v_y from the identified model
    with a margin; the steering bound holds the largest recorded demand, a margin, and 0.05 rad of steering
    fault; and |F_yf| at most the grip of a dry road (mu = 1.2). The box is the domain the certificate covers:
    the vehicle may leave the recordings' envelope (a tighter turn, a lower speed) without leaving the design's,
    where it would be flagged out of domain.

    Parameters
    ----------
    prepared : sequence of _Prepared
        The recordings, prepared for the fits.
    sims : sequence of (v_y, r, delta) tuples of ndarray
        The identified model's lateral speed [m/s], yaw rate [rad/s] and road-wheel angle [rad] on each.
    params : VehicleParams
        The identified vehicle.
    offset : float
        The fitted steering offset [rad].

    Returns
    -------
    OperatingBounds
        The box.
    """
    vx = np.concatenate([p.v_x_raw[p.moving] for p in prepared])
    r = np.concatenate([p.r[p.moving] for p in prepared])
    steer = np.concatenate([p.steer[p.moving] for p in prepared])
    vy = np.concatenate([sim[0][p.moving] for p, sim in zip(prepared, sims, strict=True)])
    paper = OperatingBounds()
    vx_min = max(2.0, min(paper.vx_min_mps, math.floor(0.8 * float(vx.min()))))
    vx_max = max(paper.vx_max_mps, math.ceil(1.2 * float(vx.max())))
    r_max = round(max(paper.r_max_radps, 1.25 * float(np.abs(r).max())), 2)
    vy_max = round(max(0.5, 1.5 * float(np.abs(vy).max())), 2)
    steer_max = round(min(1.0, 1.2 * float(np.abs(steer).max()) + abs(offset) + 0.05), 3)
    L = params.front_axle_distance_m + params.rear_axle_distance_m
    grip = 1.2 * params.mass_kg * GRAVITY * params.rear_axle_distance_m / L
    return OperatingBounds(
        vx_min_mps=vx_min,
        vx_max_mps=max(vx_max, vx_min + 5),
        vy_min_mps=-vy_max,
        vy_max_mps=vy_max,
        r_min_radps=-r_max,
        r_max_radps=r_max,
        steer_max_rad=steer_max,
        front_lateral_force_max_n=round(grip, -1),
    )


# ------------------------------------------------------------------------------------------- statistics


def _autocorrelation_factor(residual: FloatArray) -> float:
    """N / N_eff >= 1 for correlated residuals (Bartlett: 1 + 2 sum of the autocorrelations up to the first
    negative one), to widen confidence intervals that assume independence."""
    x = residual - residual.mean()
    var = float(np.dot(x, x))
    if x.size < 3 or var == 0.0:
        return 1.0
    total = 1.0
    for lag in range(1, min(x.size - 1, 500)):
        rho = float(np.dot(x[:-lag], x[lag:])) / var
        if rho <= 0:
            break
        total += 2.0 * rho
    return total


def _covariance(jac: FloatArray, residual: FloatArray, inflation: float) -> FloatArray:
    """sigma^2 (J^T J)^-1 with sigma^2 the residual variance, times the autocorrelation inflation."""
    dof = max(residual.size - jac.shape[1], 1)
    sigma2 = float(np.dot(residual, residual)) / dof
    JtJ = jac.T @ jac
    return sigma2 * inflation * np.linalg.pinv(JtJ)


def _log_estimate(log_value: float, var: float) -> Estimate:
    sd = math.sqrt(max(var, 0.0))
    return Estimate(math.exp(log_value), math.exp(log_value - 1.96 * sd), math.exp(log_value + 1.96 * sd))


def _unidentified(name: str, est: Estimate, limit: float, params: VehicleParams) -> str:
    turns = "add turns entered and left briskly, lane changes or a slalom"
    if params.cg_height_m == 0.0:
        turns += (
            "; if the drives brake or accelerate in turns, give the data sheet's cg_height_m (the load "
            "transfer then explains what the stiffnesses cannot)"
        )
    why = {
        "effective_mass_kg": (
            "drive with firmer accelerations and braking, on level ground or with the road's grade (a grade column), "
            "and state the load the vehicle carried (payload_kg)"
        ),
        "front_cornering_stiffness_npr": turns,
        "rear_cornering_stiffness_npr": turns,
        "yaw_inertia_kgm2": "give yaw_inertia_kgm2 in the base profile, or add brisk steering changes",
    }[name]
    return (
        f"the recordings cannot identify {name}: {est.value:.4g} with a 95 % interval {est.low:.4g} to "
        f"{est.high:.4g} (+-{est.relative_half_width:.0%}, at most +-{limit:.0%} accepted); {why}"
    )


__all__ = [
    "IDENTIFIED_FIELDS",
    "REQUIRED_BASE_FIELDS",
    "CalibrationOptions",
    "CalibrationRefused",
    "CalibrationResult",
    "Drive",
    "Estimate",
    "calibrate",
    "operating_bounds",
]

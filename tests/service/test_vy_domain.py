"""The out-of-domain alarm from the estimated v_y alone: the premise (v_x, r) stays inside its box.

A vehicle in a steady, hard turn near the top speed has a lateral speed far
beyond the design's v_y bounds while its measured v_x and r are inside the
premise box. The engine must raise the out-of-domain WARN from the estimated
v_y; the same turn at a lower speed, whose v_y stays inside, must raise nothing.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from agv_protocol.wire import Estimate, Measurement, vehicle_key
from service.fleet import EngineConfig, FleetEngine
from service.fleet.alarms import AlarmChange
from service.profiles import ProfileSpec
from synth.gains import ObserverGains
from synth.model import continuous_dynamics
from synth.params import OperatingBounds, VehicleParams
from tests.service.helpers import FAST_DESIGN, PERIOD_NS, T0_NS

#: 6 s of samples at 100 Hz: the observer converges and the alarm persists well within it.
N_SAMPLES = 600
#: The computed steady turn is an equilibrium of eqs. (1)-(2) [state units / s].
EQUILIBRIUM_ATOL = 1e-9
#: The converged v_y estimate against the true v_y of the turn [m/s].
VY_ESTIMATE_ATOL_MPS = 0.01
#: The converged fault estimates of a fault-free turn stay below these: [N m], [rad].
QUIET_TORQUE_NM, QUIET_STEER_RAD = 1.0, 1e-3


def steady_turn(speed_mps: float, yaw_rate_radps: float, p: VehicleParams) -> tuple[float, float, float]:
    """The equilibrium of eqs. (1)-(2) at (v_x, r), no fault, no wind: (v_y [m/s], T_d [N m], delta_d [rad])."""
    k = p.symbols()
    v_x, r = speed_mps, yaw_rate_radps
    # dr/dt = 0: l_f F_yf = l_r F_yr; then dv_y/dt = 0 with F_yr = 2 C_r (l_r r - v_y) / v_x reads
    # C_y v_y^2 + c_1 v_y - c_0 = 0, c_1 = 2 C_r (1 + l_r / l_f) / v_x, c_0 = (c_1 l_r - M_v v_x) r
    c_1 = 2.0 * k["C_r"] * (1.0 + k["l_r"] / k["l_f"]) / v_x
    c_0 = (c_1 * k["l_r"] - k["M_v"] * v_x) * r
    v_y = (-c_1 + np.sqrt(c_1**2 + 4.0 * k["C_y"] * c_0)) / (2.0 * k["C_y"])  # the root near c_0 / c_1
    F_yf = k["l_r"] / k["l_f"] * 2.0 * k["C_r"] * (k["l_r"] * r - v_y) / v_x
    # eq. (2): F_yf = 2 C_f (delta - (v_y + l_f r) / v_x)
    steer = F_yf / (2.0 * k["C_f"]) + (v_y + k["l_f"] * r) / v_x
    # eq. (1): dv_x/dt = (T / R_w - C_x v_x^2) / m_eff + v_y r = 0 (the paper's profile: R_w = 1 m, m_eff = I_e)
    torque = k["R_w"] * (k["C_x"] * v_x**2 - k["m_eff"] * v_y * r)
    residual = continuous_dynamics([v_x, v_y, r], [torque, steer], 0.0, [0.0, 0.0], p)
    np.testing.assert_allclose(residual, 0.0, atol=EQUILIBRIUM_ATOL)
    return float(v_y), float(torque), float(steer)


def drive_steady_turn(
    gains: ObserverGains, speed_mps: float, yaw_rate_radps: float
) -> tuple[list[Estimate], list[AlarmChange]]:
    """Constant measurements of a steady turn into a fresh engine (default alarm rules); its estimates and alarms."""
    engine = FleetEngine(EngineConfig())
    engine.add_profile("default", ProfileSpec.model_validate({"design": FAST_DESIGN}))
    engine.activate("default", gains)
    _, torque, steer = steady_turn(speed_mps, yaw_rate_radps, VehicleParams())
    key = vehicle_key("v", "meas")
    estimates: list[Estimate] = []
    alarms: list[AlarmChange] = []
    for k in range(N_SAMPLES):
        sample = Measurement("v", k, T0_NS + k * PERIOD_NS, speed_mps, yaw_rate_radps, torque, steer)
        result = engine.process([(key, sample.encode())])
        estimates.extend(cast(Estimate, Estimate.decode(payload)) for _, payload in result.estimates)
        alarms.extend(result.alarms)
    return estimates, alarms


def test_estimated_vy_beyond_its_bounds_raises_out_of_domain_with_the_premise_inside(fast_gains: ObserverGains) -> None:
    bounds = OperatingBounds()
    speed_mps, yaw_rate_radps = 29.5, 0.54  # inside [5, 30] m/s and [-0.55, 0.55] rad/s
    assert bounds.vx_min_mps <= speed_mps <= bounds.vx_max_mps
    assert bounds.r_min_radps <= yaw_rate_radps <= bounds.r_max_radps
    true_vy, _, _ = steady_turn(speed_mps, yaw_rate_radps, VehicleParams())
    assert true_vy < bounds.vy_min_mps - 0.2  # about -1.75 m/s

    estimates, alarms = drive_steady_turn(fast_gains, speed_mps, yaw_rate_radps)
    assert len(estimates) == N_SAMPLES
    assert all(e.in_domain for e in estimates)  # the premise never left its box
    events = [c.event for c in alarms]
    assert [(a.kind, a.state, a.level) for a in events] == [("out_of_domain", "raised", "WARN")]
    raised = events[0]
    raised_seq = (raised.t_ns - T0_NS) // PERIOD_NS
    by_seq = {e.seq: e for e in estimates}
    assert by_seq[raised_seq].vy < bounds.vy_min_mps
    # raised only after the estimate had been outside for out_of_domain_after_s (0.5 s by default)
    persistence = ProfileSpec.model_validate({"design": FAST_DESIGN}).alarms.out_of_domain_after_s
    first_outside = min(e.seq for e in estimates if e.vy < bounds.vy_min_mps)
    assert (raised_seq - first_outside + 1) * PERIOD_NS / 1e9 >= persistence
    # the estimate is the true lateral speed, not a numerical excursion; the faults stay near zero
    np.testing.assert_allclose(estimates[-1].vy, true_vy, atol=VY_ESTIMATE_ATOL_MPS)
    assert abs(estimates[-1].torque_fault) < QUIET_TORQUE_NM and abs(estimates[-1].steer_fault) < QUIET_STEER_RAD
    assert estimates[-1].level == "WARN"


def test_the_same_turn_slower_keeps_vy_inside_and_raises_nothing(fast_gains: ObserverGains) -> None:
    bounds = OperatingBounds()
    speed_mps, yaw_rate_radps = 20.0, 0.54
    true_vy, _, _ = steady_turn(speed_mps, yaw_rate_radps, VehicleParams())
    assert bounds.vy_min_mps + 0.2 < true_vy < bounds.vy_max_mps - 0.2

    estimates, alarms = drive_steady_turn(fast_gains, speed_mps, yaw_rate_radps)
    assert alarms == []
    assert all(e.in_domain and bounds.vy_min_mps < e.vy < bounds.vy_max_mps for e in estimates)
    assert estimates[-1].level == "OK"

"""The physical longitudinal model: wheel torque, effective mass, rolling resistance and cornering drag.

The N-TS model must stay exact with the new terms, the DMVT bounds of the cornering drag must hold for
the observer's saturated evaluation, designs with it must be certified, and the runtime step must
implement eq. (19) with phi_c as written. Profiles of the paper keep their hashes.
"""

import dataclasses
import json

import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as hst

from edge_client.plant import PlantSimulator
from edge_client.scenario import Manoeuvre, Scenario
from synth.augmented import AugmentedModel, front_force_bound_n
from synth.design import synthesize
from synth.errors import ShapeError
from synth.fuzzy import ConventionalTSModel, NTSModel
from synth.gains import ObserverGains
from synth.model import (
    continuous_dynamics,
    continuous_matrices,
    euler_step,
    lagged_steer,
    longitudinal_resistance_n,
    state_matrix,
)
from synth.observer import FuzzyObserver, RuntimeGains, initial_observer_state, observer_step
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams
from tests.calibration_data import CAR as CALIBRATION_CAR
from tests.synth import strategies as st
from tests.tolerances import (
    FORMULA_EQUALITY_ATOL,
    FORMULA_EQUALITY_RTOL,
    LAST_BITS_ATOL,
    MODEL_EQUALITY_ATOL,
    OBSERVER_EQUATION_TOL,
    QUADRATURE_RTOL,
)

#: The calibration tests' car (a torque at a 0.33 m wheel, rolling resistance, cornering drag), with an ideal
#: steering actuator: the runtime test below feeds the demand to the model directly.
CAR = CALIBRATION_CAR.model_copy(update={"steer_time_constant_s": 0.0})
CAR_BOUNDS = OperatingBounds(vx_min_mps=6.0, vy_min_mps=-1.0, vy_max_mps=1.0, steer_max_rad=0.15)
NTS = NTSModel.build(CAR, CAR_BOUNDS)


@settings(max_examples=300, deadline=None)
@given(st.speed, st.lateral, st.yaw, st.torque, st.steer, st.wind, st.torque_fault, st.steer_fault)
def test_nts_model_with_the_new_terms_equals_the_euler_step(vx, vy, r, T, d, w, Tf, df):
    """The exactness of eq. (15) covers the wheel radius, the rolling resistance and the cornering drag."""
    x, u, f = np.array([vx, vy, r]), np.array([T, d]), np.array([Tf, df])
    np.testing.assert_allclose(NTS.step(x, u, w, f), euler_step(x, u, w, f, CAR), rtol=0, atol=MODEL_EQUALITY_ATOL)


@settings(max_examples=200, deadline=None)
@given(st.speed, st.lateral, st.yaw, st.torque, st.steer, st.wind, st.torque_fault, st.steer_fault)
def test_matrix_form_plus_the_longitudinal_resistance_is_the_physics(vx, vy, r, T, d, w, Tf, df):
    x, u, f = np.array([vx, vy, r]), np.array([T, d]), np.array([Tf, df])
    cm = continuous_matrices(CAR)
    steer = d + CAR.steer_fault_gain * df
    resistance = longitudinal_resistance_n(x, steer, CAR)
    matrix_form = state_matrix(x, CAR) @ x + cm.B_v @ u + cm.D_v[:, 0] * w + cm.F_v @ f
    matrix_form[0] -= resistance / CAR.effective_mass_kg
    np.testing.assert_allclose(
        continuous_dynamics(x, u, w, f, CAR), matrix_form, rtol=FORMULA_EQUALITY_RTOL, atol=FORMULA_EQUALITY_ATOL
    )


def test_the_drive_torque_acts_at_the_wheel_radius_on_the_effective_mass():
    """Straight at 20 m/s: the torque that holds the speed is R_w (C_x v^2 + F_r); 100 N m more accelerates
    the effective mass by 100 / R_w / m_eff."""
    v = 20.0
    hold = CAR.wheel_radius_m * (CAR.longitudinal_drag_coeff * v**2 + CAR.rolling_resistance_n)
    x = np.array([v, 0.0, 0.0])
    assert continuous_dynamics(x, [hold, 0.0], 0.0, [0.0, 0.0], CAR)[0] == pytest.approx(0.0, abs=1e-12)
    accel = continuous_dynamics(x, [hold + 100.0, 0.0], 0.0, [0.0, 0.0], CAR)[0]
    assert accel == pytest.approx(100.0 / CAR.wheel_radius_m / CAR.effective_mass_kg, rel=1e-12)


def test_cornering_drag_is_the_front_lateral_force_projected_on_the_x_axis():
    """In a steady left turn the front tyres pull back by F_yf sin(delta): hundreds of N at 7 m/s^2."""
    v, delta = 15.0, 0.075
    # the steady turn: dv_y/dt = dr/dt = 0 of eqs. (1)-(2) at this speed and steering angle
    lateral = scipy.optimize.fsolve(
        lambda vy_r: continuous_dynamics([v, *vy_r], [0.0, delta], 0.0, [0.0, 0.0], CAR)[1:], [0.0, 0.3], xtol=1e-12
    )
    x = np.array([v, *lateral])
    assert 6.0 < v * x[2] < 8.0  # about 7 m/s^2 of lateral acceleration
    F_yf = 2 * CAR.front_cornering_stiffness_npr * (delta - (x[1] + CAR.front_axle_distance_m * x[2]) / v)
    assert longitudinal_resistance_n(x, delta, CAR) == pytest.approx(CAR.rolling_resistance_n + F_yf * np.sin(delta))
    assert 200.0 < F_yf * np.sin(delta) < 600.0
    paper = VehicleParams()
    assert longitudinal_resistance_n(x, delta, paper) == 0.0  # the paper's model has neither term


def test_the_conventional_8_rule_model_refuses_terms_it_does_not_have():
    with pytest.raises(ValueError, match="no rolling resistance"):
        ConventionalTSModel.build(CAR, CAR_BOUNDS)


def test_dmvt_terms_of_the_cornering_drag():
    aug = AugmentedModel.build(NTS, 1)
    names = [t.name for t in aug.dmvt_terms]
    assert names == ["d(v_y^2)/dv_y", "dphi_c/dv_y", "dphi_c/ddelta_f"]
    _, vy_term, df_term = aug.dmvt_terms
    two_C_f, V_max, d_max = 2 * CAR.front_cornering_stiffness_npr, 1 / 6.0, 0.15
    assert vy_term.high == pytest.approx(two_C_f * V_max * np.sin(d_max)) and vy_term.low == -vy_term.high
    assert df_term.high == pytest.approx(two_C_f * np.sin(d_max) + front_force_bound_n(NTS))
    # they enter through G_c, the v_x row, and multiply the v_y and delta_f errors
    np.testing.assert_array_equal(np.flatnonzero(vy_term.matrix()), [1])
    np.testing.assert_array_equal(np.flatnonzero(df_term.matrix()), [4])
    # a physical bound on F_yf tightens the steering term, never the v_y term
    tight = AugmentedModel.build(NTSModel.build(CAR, CAR_BOUNDS.model_copy(update={"front_lateral_force_max_n": 8e3})))
    assert tight.dmvt_terms[2].high == pytest.approx(two_C_f * np.sin(d_max) + 8e3)
    assert tight.dmvt_terms[2].high < df_term.high
    assert tight.dmvt_terms[1].high == vy_term.high


@settings(max_examples=400, deadline=None)
@given(
    hst.floats(6.0, 30.0),
    hst.floats(-1.0, 1.0),
    hst.floats(-0.55, 0.55),
    hst.floats(-0.15, 0.15),
    hst.floats(-4.0, 4.0),
    hst.floats(-0.4, 0.4),
    hst.sampled_from([None, 6e3]),
)
def test_the_observer_evaluation_of_phi_c_stays_inside_the_dmvt_bounds(vx, vy, r, delta, vy_hat, delta_hat, F_max):
    """For true values in the box and any estimate (far outside too), phi_c - phi_c_hat = rho_vy e_vy +
    rho_deltaf e_deltaf for some rho in the box: |difference| <= radius_vy |e_vy| + radius_df |e_deltaf|."""
    bounds = CAR_BOUNDS.model_copy(update={"front_lateral_force_max_n": F_max})
    nts = NTSModel.build(CAR, bounds)
    x = np.array([vx, vy, r])
    F_true = 2 * CAR.front_cornering_stiffness_npr * (delta - (vy + CAR.front_axle_distance_m * r) / vx)
    if F_max is not None and abs(F_true) > F_max:
        return  # the true state is outside the operating domain the bound declares
    _, vy_term, df_term = AugmentedModel.build(nts, 1).dmvt_terms
    # the observer's evaluation (synth.observer._cornering_drag): saturate delta, v_y, then F_yf
    d_sat = np.clip(delta_hat, -0.15, 0.15)
    vy_sat = np.clip(vy_hat, -1.0, 1.0)
    F_hat = 2 * CAR.front_cornering_stiffness_npr * (d_sat - (vy_sat + CAR.front_axle_distance_m * r) / vx)
    F_hat = np.clip(F_hat, -front_force_bound_n(nts), front_force_bound_n(nts))
    difference = nts.phi_c(x, delta) - F_hat * np.sin(d_sat)
    reach = vy_term.high * abs(vy - vy_hat) + df_term.high * abs(delta - delta_hat) / CAR.steer_fault_gain
    assert abs(difference) <= reach * (1 + 1e-9) + 1e-9


def test_renamed_inertia_still_loads_and_the_papers_gains_keep_their_hash():
    old = {"mass_kg": 1481.0, "longitudinal_inertia_kgm2": 500.0}
    assert VehicleParams.model_validate(old).effective_mass_kg == 500.0
    with pytest.raises(ValueError, match="not both"):
        VehicleParams.model_validate({**old, "effective_mass_kg": 500.0})
    hashed = VehicleParams().hashed()
    assert hashed["longitudinal_inertia_kgm2"] == 443.0
    assert not {"effective_mass_kg", "wheel_radius_m", "rolling_resistance_n", "cornering_drag"} & hashed.keys()
    assert "steer_max_rad" not in OperatingBounds().hashed()
    assert {"wheel_radius_m", "cornering_drag", "effective_mass_kg"} <= CAR.hashed().keys()


@pytest.fixture(scope="module")
def car_gains() -> ObserverGains:
    return synthesize(CAR, CAR_BOUNDS.model_copy(update={"front_lateral_force_max_n": 8e3}), DesignOptions())


def test_a_design_with_the_cornering_drag_is_certified_on_every_vertex(car_gains):
    c = car_gains.certificate
    assert c.verified and c.spectral_radius_max <= c.decay_rate < 1.0
    # 4 rules x 4 next rules x 2^3 rho vertices, for each of the two gain sets
    assert c.n_lmis_verified == 2 * 4 * 4 * 8 and min(c.lmi_min_eigenvalues) > 0
    assert {"dphi_c/dv_y", "dphi_c/ddelta_f"} <= c.spectral_radius_at.keys()
    again = ObserverGains.from_dict(json.loads(json.dumps(car_gains.to_dict())))
    assert again.version == car_gains.version


def test_the_runtime_step_is_eq_19_with_the_cornering_drag(car_gains):
    """The batched GEMM equals eq. (19) written out: sum_i h_i (N_i z + L_i y) + M T1 (g + B u) + M G phi +
    M G_c phi_c, with phi_c evaluated at the saturated estimates."""
    g = car_gains
    quiet = g.quiet_gains()  # the runtime's quiet set, where no switching state is involved
    rt = RuntimeGains.from_gains(quiet)
    rng = np.random.default_rng(0)
    nv = 64
    y = np.column_stack([rng.uniform(7, 25, nv), rng.uniform(-0.5, 0.5, nv)])
    u = np.column_stack([rng.uniform(-600, 600, nv), rng.uniform(-0.12, 0.12, nv)])
    x_hat0 = np.column_stack([y[:, 0], rng.uniform(-0.8, 0.8, nv), y[:, 1]])
    z = initial_observer_state(rt, y, x_hat0)
    z[:, 3:5] = np.column_stack([rng.uniform(-50, 50, nv), rng.uniform(-0.03, 0.03, nv)])
    z_next, _ = observer_step(rt, z, y, u)
    aug = quiet.model
    nts = aug.nts
    h = nts.memberships(nts.premise(y[:, 0], y[:, 1]))
    x_hat = z - y @ quiet.E.T
    delta = np.clip(u[:, 1] + CAR.steer_fault_gain * x_hat[:, 4], -0.15, 0.15)
    vy = np.clip(x_hat[:, 1], -1.0, 1.0)
    F = 2 * CAR.front_cornering_stiffness_npr * (delta - (vy + CAR.front_axle_distance_m * y[:, 1]) / y[:, 0])
    phi_c = np.clip(F, -8e3, 8e3) * np.sin(delta)
    MT1 = quiet.M @ aug.T1
    expected = (
        np.einsum("vi,ijk,vk->vj", h, quiet.N, z)
        + np.einsum("vi,ijk,vk->vj", h, quiet.L, y)
        + (nts.g(y[:, 0], y[:, 1]) + u @ nts.B.T) @ MT1.T
        + (vy**2)[:, None] * (quiet.M @ aug.G_bar)[:, 0]
        + phi_c[:, None] * (quiet.M @ aug.G_c_bar)[:, 0]
    )
    np.testing.assert_allclose(z_next, expected, rtol=OBSERVER_EQUATION_TOL, atol=OBSERVER_EQUATION_TOL)


def test_the_step_names_a_batch_of_the_wrong_shape(car_gains):
    rt = RuntimeGains.from_gains(car_gains)
    z = np.zeros((3, rt.n))
    expected = "Incompatible dimensions of u matrix; expected \\(3, 2\\) but found \\(3, 3\\)"
    with pytest.raises(ShapeError, match=expected):
        observer_step(rt, z, np.ones((3, 2)), np.ones((3, 3)))
    with pytest.raises(ShapeError, match="of z matrix"):
        observer_step(rt, z[:2], np.ones((3, 2)), np.ones((3, 2)))


def test_the_lagged_steering_is_the_exact_mean_of_a_first_order_actuator():
    """A step of the demand at k = 0 from rest: delta_k = 1 - a^k at the samples, and the model's input is the
    mean over each sample, 1 - a^k (tau / s)(1 - a)."""
    p = VehicleParams(steer_time_constant_s=0.04)
    a = np.exp(-0.01 / 0.04)
    got = lagged_steer(np.ones(50), p, initial_rad=0.0)
    k = np.arange(50)
    np.testing.assert_allclose(got, 1.0 - a**k * (0.04 / 0.01) * (1.0 - a), rtol=0, atol=LAST_BITS_ATOL)
    # the mean, by quadrature of the continuous lag 1 - exp(-t / tau) over [t_k, t_k+1)
    t = np.linspace(0.0, 0.01, 20001)
    np.testing.assert_allclose(got[3], np.trapezoid(1.0 - np.exp(-(0.03 + t) / 0.04), t) / 0.01, rtol=QUADRATURE_RTOL)
    np.testing.assert_array_equal(lagged_steer(np.arange(5.0), VehicleParams()), np.arange(5.0))  # ideal actuator


def test_the_plants_actuator_follows_the_same_lag():
    """The plant integrates the continuous lag inside its RK4 substeps; at the samples it is the exact lag."""
    params = CAR.model_copy(update={"steer_time_constant_s": 0.05})
    scenario = Scenario(
        name="step-steer",
        duration_s=1.0,
        initial_speed_mps=15.0,
        vehicle=params,
        manoeuvres=[Manoeuvre(kind="turn", start_s=0.2, duration_s=0.8, amplitude_rad=0.02, ramp_s=0.0)],
    )
    plant = PlantSimulator([scenario], prefetch=False)
    angles, demands = [], []
    for _ in range(100):
        sample = plant.step()
        demands.append(sample.u[0, 1])
        angles.append(float(plant.steer_angle[0]))
    a = params.steer_lag_factor
    expected, state = [], demands[0]
    for d in demands:
        state = a * state + (1 - a) * d
        expected.append(state)
    np.testing.assert_allclose(angles, expected, rtol=0, atol=FORMULA_EQUALITY_ATOL)


def test_an_observer_with_a_lag_is_the_lag_free_observer_fed_the_lagged_demand(car_gains):
    """The actuator model is a known prefilter: the certified observer's state and gains are unchanged."""
    lagged_params = car_gains.params.model_copy(update={"steer_time_constant_s": 0.04})
    with_lag = dataclasses.replace(car_gains, params=lagged_params)
    rng = np.random.default_rng(1)
    K = 300
    y = np.column_stack([15.0 + 0.01 * rng.standard_normal(K), 0.1 * np.sin(np.arange(K) / 40.0)])
    u = np.column_stack([200.0 + 20 * rng.standard_normal(K), 0.03 * np.sin(np.arange(K) / 40.0)])
    lagged = u.copy()
    lagged[:, 1] = lagged_steer(u[:, 1], lagged_params)
    a = FuzzyObserver(with_lag, y[:1], None, u[:1])
    b = FuzzyObserver(car_gains, y[:1])
    assert a.z.shape[1] == b.z.shape[1] + 1
    for k in range(K):
        ra, rb = a.step(y[k : k + 1], u[k : k + 1]), b.step(y[k : k + 1], lagged[k : k + 1])
        np.testing.assert_allclose(ra.x_hat, rb.x_hat, rtol=FORMULA_EQUALITY_RTOL, atol=FORMULA_EQUALITY_ATOL)


def test_the_paper_profile_keeps_the_designs_made_before_the_physical_fields():
    """The paper's profile hashes as it did when the effective mass was named longitudinal_inertia_kgm2 and the
    new fields did not exist: its stored gains keep their versions."""
    p = VehicleParams()
    legacy_params = {k: v for k, v in p.model_dump().items() if k not in ("wheel_radius_m", "rolling_resistance_n",
                     "cornering_drag", "steer_time_constant_s", "cg_height_m", "effective_mass_kg")}  # fmt: skip
    legacy_params["longitudinal_inertia_kgm2"] = 443.0
    bounds = {k: v for k, v in OperatingBounds().model_dump().items() if k not in ("steer_max_rad",
              "front_lateral_force_max_n")}  # fmt: skip
    assert p.hashed() == legacy_params and OperatingBounds().hashed() == bounds
    physical = p.model_copy(update={"wheel_radius_m": 0.3})
    assert physical.hashed() != legacy_params

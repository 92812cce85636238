import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as hst

from synth.fuzzy import ConventionalTSModel, NTSModel
from synth.model import euler_step
from synth.params import OperatingBounds, VehicleParams
from tests.synth import strategies as st
from tests.tolerances import MODEL_EQUALITY_ATOL, SIMPLEX_ATOL

P = VehicleParams()
B = OperatingBounds()
NTS = NTSModel.build(P, B)
TS8 = ConventionalTSModel.build(P, B)


@settings(max_examples=300, deadline=None)
@given(st.speed, st.lateral, st.yaw, st.torque, st.steer, st.wind, st.torque_fault, st.steer_fault)
def test_nts_model_equals_euler_step_of_nonlinear_model(vx, vy, r, T, d, w, Tf, df):
    """Eq. (15) with the corrected consequent reproduces eq. (12) everywhere in S_x."""
    x = np.array([vx, vy, r])
    u = np.array([T, d])
    f = np.array([Tf, df])
    np.testing.assert_allclose(NTS.step(x, u, w, f), euler_step(x, u, w, f, P), rtol=0, atol=MODEL_EQUALITY_ATOL)


@settings(max_examples=200, deadline=None)
@given(st.speed, st.lateral, st.yaw, st.torque, st.steer, st.wind, st.torque_fault, st.steer_fault)
def test_conventional_8_rule_model_equals_euler_step(vx, vy, r, T, d, w, Tf, df):
    x = np.array([vx, vy, r])
    u = np.array([T, d])
    f = np.array([Tf, df])
    np.testing.assert_allclose(TS8.step(x, u, w, f), euler_step(x, u, w, f, P), rtol=0, atol=MODEL_EQUALITY_ATOL)


@settings(max_examples=300, deadline=None)
@given(st.speed, st.yaw)
def test_memberships_lie_on_the_simplex(vx, r):
    h = NTS.memberships(NTS.premise(vx, r))
    assert h.shape == (4,)
    assert np.all(h >= -SIMPLEX_ATOL) and np.all(h <= 1 + SIMPLEX_ATOL)
    assert abs(h.sum() - 1.0) < SIMPLEX_ATOL


@settings(max_examples=100, deadline=None)
@given(st.speed, st.speed, st.lateral)
def test_eight_rule_memberships_lie_on_the_simplex(vx, other, vy):
    h = TS8.memberships(np.array([vx, 1.0 / other, vy]))
    assert np.all(h >= -SIMPLEX_ATOL) and abs(h.sum() - 1.0) < SIMPLEX_ATOL


def test_memberships_select_the_vertices_at_the_corners():
    V_lo, V_hi = B.inverse_speed_bounds
    corners = [(V_lo, B.r_min_radps), (V_lo, B.r_max_radps), (V_hi, B.r_min_radps), (V_hi, B.r_max_radps)]
    for i, (V, r) in enumerate(corners):
        np.testing.assert_allclose(NTS.memberships(np.array([V, r])), np.eye(4)[i], atol=SIMPLEX_ATOL)


@given(hst.floats(6.0, 60.0), hst.floats(0.2, 1.0))
@settings(max_examples=25, deadline=None)
def test_vertices_follow_the_bounds(vx_max, r_max):
    """The vertex matrices are computed from the bounds, never typed in."""
    bounds = OperatingBounds(vx_max_mps=vx_max, r_min_radps=-r_max, r_max_radps=r_max)
    model = NTSModel.build(P, bounds)
    assert model.A[0, 0, 1] == -0.01 * r_max and model.A[1, 0, 1] == 0.01 * r_max
    expected = 1 - 0.01 * 2 * (P.front_cornering_stiffness_npr + P.rear_cornering_stiffness_npr) / P.mass_kg / vx_max
    assert abs(model.A[0, 1, 1] - expected) < 1e-15


def test_corrected_consequent_terms():
    """g_1 divides by I_e (the effective mass), s multiplies both terms of g_2, g_3 carries r (NOTES.md)."""
    vx, r = 12.0, 0.2
    g = NTS.g(vx, r)
    k = P.symbols()
    assert g[0] == -0.01 * k["C_x"] * vx**2 / k["m_eff"]
    assert abs(g[1] - 0.01 * (2 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / (k["M_v"] * vx) - vx) * r) < 1e-16
    assert abs(g[2] + 0.01 * 2 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / (k["I_z"] * vx) * r) < 1e-16
    assert np.all(NTS.g(vx, 0.0)[1:] == 0.0)


def test_premise_clipping_and_domain_flag():
    xi = NTS.premise(np.array([3.0, 10.0, 40.0]), np.array([0.0, 0.7, 0.1]))
    np.testing.assert_array_equal(NTS.in_domain(xi), [False, False, False])
    clipped = NTS.clip_premise(xi)
    assert np.all(NTS.in_domain(clipped))

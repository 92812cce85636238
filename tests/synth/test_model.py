import numpy as np
from hypothesis import given, settings

from synth.model import continuous_dynamics, continuous_matrices, euler_step, rk4_step, state_matrix
from synth.params import VehicleParams
from tests.synth import strategies as st
from tests.tolerances import FORMULA_EQUALITY_ATOL, FORMULA_EQUALITY_RTOL, MODEL_EQUALITY_ATOL

P = VehicleParams()


@settings(max_examples=200, deadline=None)
@given(st.speed, st.lateral, st.yaw, st.torque, st.steer, st.wind, st.torque_fault, st.steer_fault)
def test_matrix_form_of_eq_6_equals_the_physics_of_eqs_1_2(vx, vy, r, T, d, w, Tf, df):
    x = np.array([vx, vy, r])
    u = np.array([T, d])
    f = np.array([Tf, df])
    cm = continuous_matrices(P)
    matrix_form = state_matrix(x, P) @ x + cm.B_v @ u + cm.D_v[:, 0] * w + cm.F_v @ f
    np.testing.assert_allclose(
        continuous_dynamics(x, u, w, f, P), matrix_form, rtol=FORMULA_EQUALITY_RTOL, atol=FORMULA_EQUALITY_ATOL
    )


def test_euler_step_is_eq_12():
    x = np.array([12.0, 0.3, -0.1])
    u = np.array([150.0, 0.02])
    f = np.array([10.0, 0.01])
    expected = x + 0.01 * continuous_dynamics(x, u, 500.0, f, P)
    np.testing.assert_allclose(euler_step(x, u, 500.0, f, P), expected, atol=MODEL_EQUALITY_ATOL)


def test_rk4_is_fourth_order():
    x = np.array([12.0, 0.3, -0.1])
    u = np.array([150.0, 0.03])
    f = np.zeros(2)

    def integrate(steps: int) -> np.ndarray:
        state = x
        for _ in range(steps):
            state = rk4_step(state, u, 0.0, f, P, 0.2 / steps)
        return state

    reference = integrate(2000)
    err_coarse = np.abs(integrate(10) - reference).max()
    err_fine = np.abs(integrate(20) - reference).max()
    assert 12.0 < err_coarse / err_fine < 20.0  # halving the step divides the error by ~16


def test_batched_evaluation_matches_single():
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(5, 30, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-0.55, 0.55, 50)])
    u = np.column_stack([rng.uniform(-500, 500, 50), rng.uniform(-0.1, 0.1, 50)])
    w = rng.uniform(-800, 800, 50)
    f = np.zeros((50, 2))
    batch = continuous_dynamics(x, u, w, f, P)
    for i in range(50):
        np.testing.assert_array_equal(batch[i], continuous_dynamics(x[i], u[i], w[i], f[i], P))

import numpy as np
import pytest

from edge_client.library import builtin_scenario
from edge_client.simulation import ekf_factory, estimate, simulate_plant
from synth.ekf import AugmentedEKF, jacobian
from synth.model import continuous_dynamics
from synth.options import NoiseModel
from synth.params import OperatingBounds, VehicleParams
from tests.tolerances import FINITE_DIFFERENCE_TOL

P = VehicleParams()


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(5, 30, 20), rng.uniform(-1.5, 1.5, 20), rng.uniform(-0.55, 0.55, 20)])
    u = np.column_stack([rng.uniform(-300, 300, 20), rng.uniform(-0.1, 0.1, 20)])
    f = np.zeros((20, 2))
    J = jacobian(x, P)
    h = 1e-6
    for j in range(3):
        dx = np.zeros(3)
        dx[j] = h
        fd = (continuous_dynamics(x + dx, u, 0.0, f, P) - continuous_dynamics(x - dx, u, 0.0, f, P)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, rtol=FINITE_DIFFERENCE_TOL, atol=FINITE_DIFFERENCE_TOL)


@pytest.fixture(scope="module")
def clean_paper_1():
    return simulate_plant([builtin_scenario("paper-1")])


def test_ekf_converges_on_a_noise_free_run(clean_paper_1, robust_gains_for_ekf):
    """A real baseline: noise-free, the EKF locks onto both faults once the transients are over."""
    result = estimate(clean_paper_1, ekf_factory(robust_gains_for_ekf))
    late = result.t >= 15.0  # after the wind gust (10-11 s) and the torque step (5 s)
    err = np.abs(result.f_hat[late, 0] - result.f[late, 0])
    assert err[:, 0].max() < 0.1 * 30.0  # torque bias of 30 N m
    assert err[:, 1].max() < 0.1 * 0.1  # steering fault amplitude 0.1 rad
    vy_rmse = np.sqrt(np.mean((result.x_hat[late, 0, 1] - result.x[late, 0, 1]) ** 2))
    assert vy_rmse < 0.02  # v_y [m/s], |v_y| up to 0.34 in this scenario


@pytest.fixture(scope="module")
def robust_gains_for_ekf():
    from synth.design import synthesize
    from synth.options import DesignOptions

    return synthesize(options=DesignOptions(design="robust", lyapunov="common", switching=None))


def test_covariance_stays_symmetric_positive_definite():
    y0 = np.array([[10.0, 0.1], [25.0, -0.2]])
    ekf = AugmentedEKF(P, OperatingBounds(), NoiseModel(), 2, y0)
    rng = np.random.default_rng(0)
    for _ in range(500):
        ekf.step(y0 + rng.normal(0, [0.05, 0.005], y0.shape), np.array([[50.0, 0.01], [200.0, 0.0]]))
    assert np.allclose(ekf.P, ekf.P.transpose(0, 2, 1))
    assert np.linalg.eigvalsh(ekf.P).min() > 0

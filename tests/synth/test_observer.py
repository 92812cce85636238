import numpy as np
import pytest

from edge_client.library import builtin_scenario
from edge_client.simulation import observer_factory, run
from synth.observer import FuzzyObserver, RuntimeGains, initial_observer_state, observer_step
from tests.tolerances import (
    AMPLIFIED_ROUNDING_ATOL,
    AMPLIFIED_ROUNDING_RTOL,
    BATCH_EQUALITY_ATOL,
    CONVERGENCE_FRACTION,
    FORMULA_EQUALITY_ATOL,
    FORMULA_EQUALITY_RTOL,
)


@pytest.mark.parametrize("name", ["paper-1", "paper-2"])
def test_fault_estimates_converge_on_noise_free_paper_scenarios(paper_gains, name):
    result = run([builtin_scenario(name)], observer_factory(paper_gains))
    rmse = result.rmse(after_s=3.0)
    amplitude = result.fault_amplitude()[0]
    assert rmse["T_f"][0] < CONVERGENCE_FRACTION * amplitude[0]
    assert rmse["delta_f"][0] < CONVERGENCE_FRACTION * amplitude[1]
    assert result.in_domain.all()


def test_batch_step_equals_single_vehicle_steps(paper_gains_order1):
    rng = np.random.default_rng(0)
    nv = 5
    y = np.column_stack([rng.uniform(6, 25, nv), rng.uniform(-0.4, 0.4, nv)])
    u = np.column_stack([rng.uniform(0, 300, nv), rng.uniform(-0.05, 0.05, nv)])
    batch = FuzzyObserver(paper_gains_order1, y)
    singles = [FuzzyObserver(paper_gains_order1, y[i : i + 1]) for i in range(nv)]
    for _ in range(20):
        result = batch.step(y, u)
        for i, obs in enumerate(singles):
            np.testing.assert_allclose(obs.step(y[i], u[i]).x_hat[0], result.x_hat[i], atol=BATCH_EQUALITY_ATOL)
        y = y + rng.normal(0, 0.01, y.shape)


def test_step_implements_algorithm_1(paper_gains_order1):
    """x_hat = z - E y; z+ = N(h) z + L(h) y + M T1 (g + B u) + M G_bar phi(x_hat), written out longhand."""
    g = paper_gains_order1
    rt = RuntimeGains.from_gains(g)
    nts = g.model.nts
    y = np.array([[14.0, 0.2]])
    u = np.array([[120.0, 0.01]])
    z = initial_observer_state(rt, y, np.array([[13.0, 0.4, 0.1]]))
    z_next, result = observer_step(rt, z, y, u)
    x_hat = z[0] - g.E @ y[0]
    h = nts.memberships(nts.premise(14.0, 0.2))
    N_h = np.einsum("i,ijk->jk", h, g.N)
    L_h = np.einsum("i,ijk->jk", h, g.L)
    expected = (
        N_h @ z[0]
        + L_h @ y[0]
        + g.M @ g.model.T1 @ (nts.g(14.0, 0.2) + nts.B @ u[0])
        + g.M @ g.model.G_bar[:, 0] * x_hat[1] ** 2
    )
    np.testing.assert_allclose(result.x_hat[0], x_hat, atol=FORMULA_EQUALITY_ATOL)
    np.testing.assert_allclose(result.x_hat[0, :3], [13.0, 0.4, 0.1], atol=FORMULA_EQUALITY_ATOL)
    np.testing.assert_allclose(z_next[0], expected, rtol=FORMULA_EQUALITY_RTOL, atol=AMPLIFIED_ROUNDING_ATOL)


def test_out_of_domain_premise_is_clipped_and_flagged(paper_gains_order1):
    obs = FuzzyObserver(paper_gains_order1, np.array([[2.0, 0.0], [12.0, 0.9], [12.0, 0.1]]))
    result = obs.step(np.array([[2.0, 0.0], [12.0, 0.9], [12.0, 0.1]]), np.zeros((3, 2)))
    np.testing.assert_array_equal(result.in_domain, [False, False, True])
    assert np.all(np.isfinite(obs.z))


def test_phi_uses_the_saturated_lateral_speed(paper_gains_order1):
    """A wild v_y estimate feeds phi(v_y_max), never v_y_hat^2 (keeps rho inside S_rho)."""
    g = paper_gains_order1
    rt = RuntimeGains.from_gains(g)
    y = np.array([[12.0, 0.1]])
    u = np.zeros((1, 2))
    far = initial_observer_state(rt, y, np.array([[12.0, 40.0, 0.1]]))
    edge = initial_observer_state(rt, y, np.array([[12.0, 1.5, 0.1]]))
    z_far, res_far = observer_step(rt, far, y, u)
    z_edge, _ = observer_step(rt, edge, y, u)
    assert not res_far.vy_in_bounds[0]
    # the difference is the linear part only: N(h) (far - edge), no phi difference
    h = g.model.nts.memberships(g.model.nts.premise(12.0, 0.1))
    linear = np.einsum("i,ijk->jk", h, g.N) @ (far - edge)[0]
    np.testing.assert_allclose(z_far[0] - z_edge[0], linear, rtol=AMPLIFIED_ROUNDING_RTOL, atol=AMPLIFIED_ROUNDING_ATOL)


def test_the_reported_estimate_adds_the_output_gain_and_leaves_the_dynamics_alone(robust_gains_default):
    """Robust gains: result.x_hat = x_hat + K (y - C_bar x_hat); z_{k+1} is what it would be without K."""
    import dataclasses

    g = robust_gains_default
    assert np.any(g.output_gain)
    rt = RuntimeGains.from_gains(g)
    rt_unfiltered = RuntimeGains.from_gains(dataclasses.replace(g, K=None))
    rng = np.random.default_rng(1)
    y = np.column_stack([rng.uniform(6, 25, 4), rng.uniform(-0.4, 0.4, 4)])
    u = np.column_stack([rng.uniform(0, 300, 4), rng.uniform(-0.05, 0.05, 4)])
    z = initial_observer_state(rt, y, np.column_stack([y[:, 0] - 0.3, rng.normal(0, 0.2, 4), y[:, 1] + 0.02]))
    z_next, result = observer_step(rt, z, y, u)
    z_plain, plain = observer_step(rt_unfiltered, z, y, u)
    np.testing.assert_array_equal(z_next, z_plain)
    expected = plain.x_hat + (y - plain.x_hat[:, [0, 2]]) @ g.output_gain.T
    np.testing.assert_allclose(result.x_hat, expected, rtol=FORMULA_EQUALITY_RTOL, atol=FORMULA_EQUALITY_ATOL)
    assert not np.allclose(result.faults, plain.faults)

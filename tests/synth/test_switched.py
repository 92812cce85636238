"""The switched robust design: a fast and a quiet gain set under one Lyapunov function, and its runtime rule."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from edge_client.faults import BiasFault
from edge_client.scenario import REALISTIC_NOISE, Scenario, SpeedPoint
from edge_client.simulation import estimate, simulate_plant
from synth.analysis import frozen_comparison
from synth.design import synthesize
from synth.errors import VerificationFailed
from synth.gains import ObserverGains
from synth.observer import FuzzyObserver, RuntimeGains, initial_observer_state, observer_step, switched_step
from synth.options import ROBUST_DECAY_RATE, SWITCHED_DECAY_RATE, DesignOptions, SwitchingRule
from tests.tolerances import AMPLIFIED_ROUNDING_RTOL, BATCH_EQUALITY_ATOL, FORMULA_EQUALITY_ATOL

RULE = SwitchingRule()


@pytest.fixture(scope="module")
def switched() -> ObserverGains:
    return synthesize(options=DesignOptions(switching=RULE))


@pytest.fixture(scope="module")
def one_set() -> ObserverGains:
    """The one-set design at the switched design's rate: its fast set."""
    return synthesize(options=DesignOptions(robust_decay_rate=SWITCHED_DECAY_RATE, switching=None))


def test_the_default_design_is_switched_at_its_own_decay_rate():
    default = DesignOptions()
    assert default.switching == RULE and default.robust_decay_rate == SWITCHED_DECAY_RATE < ROBUST_DECAY_RATE
    one = DesignOptions(switching=None)
    assert one.switching is None and one.robust_decay_rate == ROBUST_DECAY_RATE
    assert DesignOptions.model_validate({"switching": {}}).robust_decay_rate == SWITCHED_DECAY_RATE
    # designs that cannot switch have one set, whatever is left out
    assert DesignOptions(design="paper").switching is None and DesignOptions(robust_cost="h2").switching is None
    # one set stays one set through a round trip (stored gain documents)
    assert DesignOptions.model_validate(one.model_dump()).switching is None
    # filled-in defaults are not marked as set: a stored profile that left them out keeps following them
    assert DesignOptions().model_dump(exclude_unset=True) == {"fault_order": 1}
    assert DesignOptions(switching={}).model_dump(exclude_unset=True) == {"fault_order": 1, "switching": {}}
    # a rate given is kept, and a stored design reads back as it was made
    assert DesignOptions(switching=RULE, robust_decay_rate=0.995).robust_decay_rate == 0.995
    stored = DesignOptions(switching=RULE, robust_decay_rate=0.996).model_dump()
    assert DesignOptions.model_validate(stored).robust_decay_rate == 0.996


def test_switching_needs_the_joint_robust_design():
    with pytest.raises(ValueError, match="switching needs design='robust'"):
        DesignOptions(design="paper", switching=RULE)
    with pytest.raises(ValueError, match="robust_cost='joint'"):
        DesignOptions(robust_cost="h2", switching=RULE)


def test_the_fast_set_is_the_one_set_design_and_the_quiet_set_is_quieter(switched, one_set):
    assert switched.switched and not one_set.switched
    np.testing.assert_array_equal(switched.N, one_set.N)
    np.testing.assert_array_equal(switched.L, one_set.L)
    perf = switched.certificate.performance
    assert perf["fast_set_h2_cost_bound"] == one_set.certificate.performance["h2_cost_bound"]
    assert perf["h2_cost_bound"] < perf["fast_set_h2_cost_bound"]
    fast, kalman = frozen_comparison(switched, 10.0)
    quiet, _ = frozen_comparison(switched.quiet_gains(), 10.0)
    assert kalman.cost <= quiet.cost < fast.cost
    assert quiet.torque_noise_nm < fast.torque_noise_nm
    # a switched design is its own version; the one-set design keeps its hash
    assert switched.version != one_set.version
    assert one_set.content_hash() == one_set.certificate.content_hash


def test_both_sets_pass_the_numpy_verification_with_one_lyapunov_function(switched):
    c = switched.certificate
    assert c.verified and c.decay_rate <= switched.options.robust_decay_rate < 1.0
    assert c.performance["quiet_set_decay_rate"] <= switched.options.robust_decay_rate
    assert c.performance["fast_set_decay_rate"] <= switched.options.robust_decay_rate
    switched.reverify()  # both sets, the stored P and R
    # the quiet set's certificate with a P that is not the stored one fails: the check is not vacuous
    broken = dataclasses.replace(switched, P=switched.P * np.linspace(0.2, 1.8, switched.P.shape[0])[:, None, None])
    with pytest.raises(VerificationFailed):
        broken.reverify()


def test_random_switching_contracts_the_common_lyapunov_function(switched):
    """For random (h, h+, rho) and either set: N^T P(h+) N <= alpha^2 P(h), design coordinates."""
    rng = np.random.default_rng(3)
    alpha = switched.options.robust_decay_rate
    nts = switched.model.nts
    (term,) = switched.model.dmvt_terms
    sets = [switched, switched.quiet_gains()]
    frames = [g.design_frame() for g in sets]
    worst = 0.0
    for _ in range(300):
        xi, xi_next = (rng.uniform(nts.premise_low, nts.premise_high) for _ in range(2))
        h, h_next = nts.memberships(xi[None])[0], nts.memberships(xi_next[None])[0]
        N_design, (MG,) = frames[rng.integers(2)]
        N = np.einsum("i,ijk->jk", h, N_design) + rng.uniform(term.low, term.high) * MG
        P_h, P_next = np.einsum("i,ijk->jk", h, switched.P), np.einsum("i,ijk->jk", h_next, switched.P)
        top = scipy.linalg.eigh(N.T @ P_next @ N, P_h, eigvals_only=True)[-1]
        worst = max(worst, float(top))
    assert worst < alpha**2


def test_round_trip_and_tampering(switched):
    doc = switched.to_dict()
    again = ObserverGains.from_dict(doc)
    assert again.version == switched.version and again.switched
    np.testing.assert_array_equal(again.quiet.L, switched.quiet.L)
    tampered = {
        **doc,
        "matrices": {**doc["matrices"], "L_quiet": (np.array(doc["matrices"]["L_quiet"]) * 1.01).tolist()},
    }
    with pytest.raises(VerificationFailed, match="content hash mismatch"):
        ObserverGains.from_dict(tampered)
    partial = {**doc, "matrices": {k: v for k, v in doc["matrices"].items() if k != "K_quiet"}}
    with pytest.raises(VerificationFailed, match="quiet set needs all"):
        ObserverGains.from_dict(partial)
    no_rule = {**doc, "options": {**doc["options"], "switching": None}}
    with pytest.raises(VerificationFailed, match="both the switching rule"):
        ObserverGains.from_dict(no_rule)


@pytest.mark.parametrize("modes", ["F..F.F.", "..F....."])  # "F": the vehicle runs the fast set
def test_a_mixed_batch_equals_each_vehicle_stepped_with_its_own_set(switched, modes):
    rt = RuntimeGains.from_gains(switched)
    quiet_rt = RuntimeGains.from_gains(switched.quiet_gains())
    nv = len(modes)
    rng = np.random.default_rng(0)
    y = np.column_stack([rng.uniform(6.0, 28.0, nv), rng.uniform(-0.4, 0.4, nv)])
    u = np.column_stack([rng.uniform(0.0, 300.0, nv), rng.uniform(-0.05, 0.05, nv)])
    z = initial_observer_state(rt, y) + rng.normal(0.0, 0.1, (nv, rt.n))
    fast = np.array([m == "F" for m in modes])
    z_next, res = observer_step(rt, z, y, u, fast)
    for i in range(nv):
        own = RuntimeGains.from_gains(switched) if fast[i] else quiet_rt
        z_i, res_i = observer_step(own, z[i : i + 1], y[i : i + 1], u[i : i + 1])
        np.testing.assert_allclose(z_next[i], z_i[0], atol=BATCH_EQUALITY_ATOL)
        np.testing.assert_allclose(res.x_hat[i], res_i.x_hat[0], atol=BATCH_EQUALITY_ATOL)
    # the innovation that came out of the GEMM is (y - C x_hat) / sigma, weighted for the statistic
    noise, rule = switched.options.noise, switched.options.switching
    assert rule is not None
    weight = np.sqrt(0.5 * (1.0 - rule.forgetting))
    expected = weight * (y - z[:, [0, 2]]) / [noise.vx_sigma_mps, noise.r_sigma_radps]
    np.testing.assert_allclose(res.innovation, expected, atol=BATCH_EQUALITY_ATOL)
    assert res.fast is fast


def test_the_rule_counts_down_and_holds_after_an_exceedance(switched):
    rt = RuntimeGains.from_gains(switched)
    assert rt.start_samples == round(RULE.start_s / switched.params.sample_period_s)
    y = np.array([[10.0, 0.0], [10.0, 0.0]])
    u = np.zeros((2, 2))
    z = initial_observer_state(rt, y)
    z[1, 0] += 2.0  # vehicle 1 far off: a v_x innovation of 40 sigma
    stat, left = np.zeros(2), np.array([0, 3])
    _, stat, left, res = switched_step(rt, z, stat, left, y, u)
    assert res.fast.tolist() == [False, True]
    assert stat[0] < RULE.threshold < stat[1]
    # from a zero statistic, s_k = (1 - lambda) |(y - C x_hat) / sigma|^2 / 2
    noise = switched.options.noise
    nu = (y - z[:, [0, 2]]) / [noise.vx_sigma_mps, noise.r_sigma_radps]
    np.testing.assert_allclose(
        stat,
        0.5 * (1.0 - RULE.forgetting) * np.sum(nu**2, axis=1),
        rtol=AMPLIFIED_ROUNDING_RTOL,
        atol=FORMULA_EQUALITY_ATOL,
    )
    assert left.tolist() == [0, rt.hold_samples]  # the exceedance holds the fast set for hold_s
    # a settled pair (both on the quiet set): the exceedance alone switches vehicle 1, the inputs stay as given
    settled_stat, settled_left = np.zeros(2), np.zeros(2, dtype=np.int64)
    _, stat, left, res = switched_step(rt, z, settled_stat, settled_left, y, u)
    assert res.fast.tolist() == [False, False] and stat[0] < RULE.threshold < stat[1]
    assert left.tolist() == [0, rt.hold_samples]
    assert settled_left.tolist() == [0, 0] and settled_stat.tolist() == [0.0, 0.0]
    # a settled pair whose estimate agrees with the measurement stays on the quiet set
    _, stat2, left2, res2 = switched_step(rt, initial_observer_state(rt, y), np.zeros(2), np.zeros(2, np.int64), y, u)
    assert res2.fast.tolist() == [False, False] and left2.tolist() == [0, 0] and stat2.max() < RULE.threshold
    one = RuntimeGains.from_gains(synthesize(options=DesignOptions(design="robust", lyapunov="common", switching=None)))
    s0, l0 = np.zeros(2), np.zeros(2, dtype=np.int64)
    _, s1, l1, plain = switched_step(one, initial_observer_state(one, y), s0, l0, y, u)
    assert s1 is s0 and l1 is l0 and plain.fast is None and plain.innovation is None


def _torque_step_scenario(seed: int) -> Scenario:
    return Scenario(
        name="torque-step",
        # measured: the quiet set alone tracks a 150 N m step with the statistic below the threshold
        description="straight at 15 m/s, 500 N m torque bias from 10 s",
        duration_s=20.0,
        initial_speed_mps=15.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=15.0),),
        faults=(BiasFault(channel="torque", onset_s=10.0, magnitude=500.0),),
        noise=REALISTIC_NOISE,
        seed=seed,
    )


def test_the_rule_switches_to_the_fast_set_on_a_fault_step_and_back(switched):
    modes: list[bool] = []

    class Recording(FuzzyObserver):
        def step(self, y, u):  # type: ignore[no-untyped-def]
            res = super().step(y, u)
            modes.append(bool(res.fast[0]))
            return res

    result = estimate(
        simulate_plant([_torque_step_scenario(1)]), lambda y0, x0, u0=None: Recording(switched, y0, x0, u0)
    )
    fast = np.array(modes)
    t = result.t
    assert fast[t < RULE.start_s].all()  # the start
    assert not fast[(t > 7.0) & (t < 10.0)].any()  # settled before the onset: quiet
    assert fast[(t >= 10.0) & (t < 11.0)].any()  # the step wakes the fast set within a second
    assert not fast[t > 17.0].any()  # and it settles back
    # the estimate converges on the step
    late = t > 15.0
    assert abs(np.median(result.f_hat[late, 0, 0]) - 500.0) < 25.0


def test_batches_on_one_set_share_read_only_masks_and_count_down(switched):
    rt = RuntimeGains.from_gains(switched)
    quiet_rt = dataclasses.replace(rt, WT=rt.WT_quiet, XT=rt.XT_quiet, WT_quiet=None, WT_pair=None)
    for nv in (3, 5):  # a larger batch after a smaller one: the shared mask grows
        y = np.column_stack([np.linspace(8.0, 20.0, nv), np.linspace(-0.1, 0.1, nv)])
        u = np.zeros((nv, 2))
        z = initial_observer_state(rt, y)
        # settled: the quiet set, an all-False mask of the batch's length that nobody can write
        z_next, _, left, res = switched_step(rt, z, np.zeros(nv), np.zeros(nv, dtype=np.int64), y, u)
        assert res.fast.tolist() == [False] * nv and not res.fast.flags.writeable
        assert left.tolist() == [0] * nv
        np.testing.assert_allclose(z_next, observer_step(quiet_rt, z, y, u)[0], atol=BATCH_EQUALITY_ATOL)
        # starting: every vehicle on the fast set, each countdown one sample shorter
        start = np.full(nv, 7, dtype=np.int64)
        z_next, _, left, res = switched_step(rt, z, np.zeros(nv), start, y, u)
        assert res.fast.tolist() == [True] * nv and not res.fast.flags.writeable
        assert left.tolist() == [6] * nv and start.tolist() == [7] * nv
        np.testing.assert_allclose(z_next, observer_step(rt, z, y, u)[0], atol=BATCH_EQUALITY_ATOL)

"""The loss-of-effectiveness stage (synth.effectiveness): alpha recovered from a simulated vehicle, the total
fault tracked without the additive design's lag, the observer untouched, and the designs it refuses."""

from __future__ import annotations

import numpy as np
import pytest

from edge_client.faults import LossOfEffectivenessFault
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario, SpeedPoint
from edge_client.simulation import PlantRecord, simulate_plant
from synth.certificate import spectral_radius_grid
from synth.cusum import cusum_threshold
from synth.effectiveness import JUMP_DRIFT, EffectivenessEstimator, EffectivenessObserver, attribute_step
from synth.errors import BadParameters, VerificationFailed
from synth.gains import ObserverGains
from synth.observer import FuzzyObserver
from synth.options import EffectivenessOptions
from tests.tolerances import AMPLIFIED_ROUNDING_ATOL, FORMULA_EQUALITY_ATOL, PAGE_TEST_RATE_RTOL

ONSET_S, RATE_PER_S, ALPHA_MIN = 8.0, 0.04, 0.6
RAMP_END_S = ONSET_S + (1.0 - ALPHA_MIN) / RATE_PER_S
#: The healthy RMS of the default design's torque estimate under realistic noise is a few N m.
OPTIONS = EffectivenessOptions(enabled=True, torque_sigma_nm=6.0, steer_sigma_rad=0.0005)


def torque_loss_scenario() -> Scenario:
    """40 s of the paper's vehicle accelerating and braking at about 2 m/s^2 between 10 and 20 m/s (the drive
    torque swings between about +900 and -900 N m), realistic sensor noise, the torque's effectiveness
    ramped from 1 to 0.6 over 10 s from t = 8 s."""
    points = [SpeedPoint(t_s=0.0, speed_mps=10.0)]
    t, speed = 1.0, 10.0
    while t < 40.0:
        points.append(SpeedPoint(t_s=t, speed_mps=speed))
        speed = 30.0 - speed
        t += 5.0
    return Scenario(
        name="torque-loss",
        duration_s=40.0,
        initial_speed_mps=10.0,
        speed_profile=tuple(points),
        faults=(
            LossOfEffectivenessFault(channel="torque", onset_s=ONSET_S, rate_per_s=RATE_PER_S, alpha_min=ALPHA_MIN),
        ),
        noise=REALISTIC_NOISE,
        seed=4,
    )


@pytest.fixture(scope="module")
def loss_drive() -> PlantRecord:
    """The drive of :func:`torque_loss_scenario`, simulated."""
    return simulate_plant([torque_loss_scenario()])


def steer_loss_scenario() -> Scenario:
    """40 s of the paper's vehicle at 15 m/s in a slalom (steering demand a sine of 0.03 rad and 4 s period from
    t = 1 s, lateral acceleration up to about 2 m/s^2), realistic sensor noise, the steering actuator's
    effectiveness ramped from 1 to 0.6 over 10 s from t = 8 s: the delivered angle shrinks to 60 % of the
    demand."""
    return Scenario(
        name="steer-loss",
        duration_s=40.0,
        initial_speed_mps=15.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=15.0),),
        manoeuvres=(Manoeuvre(kind="slalom", start_s=1.0, duration_s=39.0, amplitude_rad=0.03, period_s=4.0),),
        faults=(
            LossOfEffectivenessFault(channel="steer", onset_s=ONSET_S, rate_per_s=RATE_PER_S, alpha_min=ALPHA_MIN),
        ),
        noise=REALISTIC_NOISE,
        seed=5,
    )


def run(gains: ObserverGains, record: PlantRecord) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(total faults, alpha, the observer's own faults), each (K, 2), stepping the observer with its stage."""
    y, u = record.y[:, 0], record.u[:, 0]
    estimator = EffectivenessObserver(gains, OPTIONS, y[:1], None, u[:1])
    out = np.zeros((3, len(record.t), 2))
    for k in range(len(record.t)):
        step = estimator.step(y[k : k + 1], u[k : k + 1])
        out[:, k] = step.faults[0], step.alpha[0], step.observer_faults[0]
    return out[0], out[1], out[2]


def test_a_torque_loss_of_effectiveness_is_recovered_and_tracked_without_the_lag(robust_gains_default, loss_drive):
    t, f = loss_drive.t, loss_drive.f[:, 0]
    total, alpha, additive = run(robust_gains_default, loss_drive)
    # the demand does swing: the drive torque is the regressor alpha is told apart from a bias by
    assert np.ptp(loss_drive.u[:, 0, 0]) > 1500.0
    # alpha within 3 % of the truth 2 s after the ramp ends, and at the end
    assert alpha[np.searchsorted(t, RAMP_END_S + 2.0), 0] == pytest.approx(ALPHA_MIN, rel=0.03)
    assert alpha[-1, 0] == pytest.approx(ALPHA_MIN, rel=0.03)
    # healthy before the onset: alpha stays near 1 on both channels
    warm = (t > OPTIONS.start_after_s) & (t < ONSET_S)
    assert np.abs(alpha[warm] - 1.0).max() < 0.05
    # the total fault tracks (alpha - 1) T_d: its RMSE after the onset at most a third of the additive design's
    after = t >= ONSET_S
    rmse = np.sqrt(np.mean((total[after] - f[after]) ** 2, axis=0))
    rmse_additive = np.sqrt(np.mean((additive[after] - f[after]) ** 2, axis=0))
    assert rmse[0] < rmse_additive[0] / 3.0
    # the observer is the additive design's, untouched: its estimates are those of the plain observer
    plain = FuzzyObserver(robust_gains_default, loss_drive.y[:1, 0], None, loss_drive.u[:1, 0])
    alone = np.array(
        [plain.step(loss_drive.y[k : k + 1, 0], loss_drive.u[k : k + 1, 0]).faults[0] for k in range(len(t))]
    )
    np.testing.assert_allclose(additive, alone, rtol=0, atol=AMPLIFIED_ROUNDING_ATOL)


def test_a_steering_loss_of_effectiveness_is_recovered_and_tracked_without_the_lag(robust_gains_default):
    """The steering twin of the torque test: a simulated vehicle whose steering actuator delivers a shrinking share
    of the demand; alpha of the steering within 3 % of the truth 2 s after the ramp ends and at the end."""
    drive = simulate_plant([steer_loss_scenario()])
    t, f = drive.t, drive.f[:, 0, 1]
    total, alpha, additive = run(robust_gains_default, drive)
    # the demand does swing, and the fault is a loss: the delivered angle is alpha times the demand
    assert np.ptp(drive.u[:, 0, 1]) > 0.05
    ends = t >= RAMP_END_S
    np.testing.assert_allclose(f[ends], (ALPHA_MIN - 1.0) * drive.u[ends, 0, 1], atol=FORMULA_EQUALITY_ATOL)
    assert alpha[np.searchsorted(t, RAMP_END_S + 2.0), 1] == pytest.approx(ALPHA_MIN, rel=0.03)
    assert alpha[-1, 1] == pytest.approx(ALPHA_MIN, rel=0.03)
    # healthy before the onset: alpha near 1 on both channels (the torque's demand barely moves at 15 m/s)
    warm = (t > OPTIONS.start_after_s) & (t < ONSET_S)
    assert np.abs(alpha[warm] - 1.0).max() < 0.05
    # the total steering fault tracks (alpha - 1) delta_d: its RMSE after the onset under a third of the additive's
    after = t >= ONSET_S
    rmse = np.sqrt(np.mean((total[after, 1] - f[after]) ** 2))
    rmse_additive = np.sqrt(np.mean((additive[after, 1] - f[after]) ** 2))
    assert rmse < rmse_additive / 3.0


def test_without_a_changing_demand_alpha_holds_and_the_total_is_the_observers(robust_gains_default, loss_drive):
    # the steering channel of that drive: a demand of zero throughout, so its alpha never moves from 1
    total, alpha, additive = run(robust_gains_default, loss_drive)
    assert np.abs(loss_drive.u[:, 0, 1]).max() == 0.0
    np.testing.assert_allclose(alpha[:, 1], 1.0, atol=FORMULA_EQUALITY_ATOL)
    np.testing.assert_allclose(total[:, 1], additive[:, 1], atol=FORMULA_EQUALITY_ATOL)


def test_the_stage_refuses_designs_it_cannot_read(paper_gains, robust_gains_default):
    with pytest.raises(BadParameters, match="fault order 1"):
        EffectivenessEstimator(paper_gains, OPTIONS, 1)
    with pytest.raises(ValueError, match="alpha_bounds"):
        EffectivenessOptions(alpha_bounds=(1.0, 1.2))
    assert EffectivenessEstimator(robust_gains_default, OPTIONS, 3).par.shape == (3, 2, 2)


def test_rows_stepped_apart_and_restarted_match_a_batch_stepped_together(robust_gains_default, loss_drive):
    """The service steps the vehicles of each tick (step_rows on a subset) and restarts single rows: three rows
    fed the same drive, one stepped with the others, one on its own in alternating ticks and one grown in later
    and reset, give the batch's estimates exactly (the reset one from its restart on, as a fresh batch)."""
    y, u = loss_drive.y[:, 0], loss_drive.u[:, 0]
    observer = FuzzyObserver(robust_gains_default, np.repeat(y[:1], 2, axis=0), None, np.repeat(u[:1], 2, axis=0))
    batch = EffectivenessEstimator(robust_gains_default, OPTIONS, 1, u[:1])
    rows = EffectivenessEstimator(robust_gains_default, OPTIONS, 1, u[:1])
    rows.grow(2)
    rows.reset(np.array([1]), u[:1])
    steps = 600
    fresh = EffectivenessEstimator(robust_gains_default, OPTIONS, 1, u[300:301])
    for k in range(steps):
        result = observer.step(np.repeat(y[k : k + 1], 2, axis=0), np.repeat(u[k : k + 1], 2, axis=0))
        f_hat, yk, uk = result.faults, y[k : k + 1], u[k : k + 1]
        want = batch.step_rows(np.array([0]), f_hat[:1], None, yk, uk)
        if k <= 300 and k % 2:  # both rows in one call, in reverse order
            got = rows.step_rows(np.array([1, 0]), f_hat[::-1], None, np.repeat(yk, 2, 0), np.repeat(uk, 2, 0))
            np.testing.assert_array_equal(got.total[1], want.total[0])
        else:
            got = rows.step_rows(np.array([0]), f_hat[:1], None, yk, uk)
            np.testing.assert_array_equal(got.total[0], want.total[0])
            again = rows.step_rows(np.array([1]), f_hat[1:], None, yk, uk)
            if k > 300:
                alone = fresh.step_rows(np.array([0]), f_hat[1:], None, yk, uk)
                np.testing.assert_array_equal(again.alpha, alone.alpha)
                np.testing.assert_array_equal(again.total, alone.total)
        if k == 300:
            rows.reset(np.array([1]), uk)
    assert not np.array_equal(batch.par[0], fresh.par[0])  # the restart did start row 1 afresh


def test_the_stage_is_verified_like_every_design(robust_gains_default):
    """The stage's recursion eps_{k+1} = N(h_k) eps_k, both gain sets of the switched default, carries a certificate
    made by the certificate builder; recomputed here on the stage's own N_i: the Lyapunov decrease for h, h+ on a
    dense premise grid with the sets switching at random, and the spectral radius on a finer grid."""
    g = robust_gains_default
    stage = EffectivenessEstimator(g, OPTIONS, 1)
    c = stage.certificate
    assert g.switched and len(stage.N) == 2
    assert c.verified and c.design == "robust+effectiveness"
    assert c.spectral_radius_max <= c.decay_rate < 1.0
    assert c.decay_rate <= c.requested_decay_rate + 1e-9
    r_rules = g.N.shape[0]
    assert c.n_lmis_verified == 2 * r_rules * g.P.shape[0] and min(c.lmi_min_eigenvalues) > 0.0
    assert c.content_hash != g.certificate.content_hash and c.content_hash == stage.verify().content_hash
    # the decrease N(h)^T P(h+) N(h) < alpha^2 P(h) in the design coordinates, sets and successors at random
    nts, T = g.model.nts, g.T
    T_inv = np.linalg.inv(T)
    V = np.linspace(nts.premise_low[0], nts.premise_high[0], 21)
    r = np.linspace(nts.premise_low[1], nts.premise_high[1], 21)
    h = nts.memberships(np.stack(np.meshgrid(V, r, indexing="ij"), axis=-1).reshape(-1, 2))
    P_h = np.einsum("gi,ijk->gjk", h, g.P)
    N_sets = [np.einsum("gi,ab,ibc,cd->gad", h, T, N, T_inv) for N in stage.N]
    rng = np.random.default_rng(0)
    worst = -np.inf
    for _ in range(4):
        pick = rng.random(len(h)) < 0.5
        N_h = np.where(pick[:, None, None], N_sets[0], N_sets[1])
        P_next = P_h[rng.permutation(len(h))]
        lhs = np.einsum("gji,gjk,gkl->gil", N_h, P_next, N_h) - c.decay_rate**2 * P_h
        worst = max(worst, float(np.linalg.eigvalsh(0.5 * (lhs + lhs.transpose(0, 2, 1))).max()))
    assert worst < 0.0
    for N in stage.N:
        radius, _, points = spectral_radius_grid(nts, N, [], (), 61)
        assert points == 61 * 61 and radius < c.decay_rate


def test_a_stage_whose_recursion_is_not_the_certified_one_is_refused(robust_gains_default):
    """The check is not vacuous: the stage with its quiet set's transitions 1 % larger, or with one rule's fast
    transition moved away from the certified ones, fails its verification with the reason."""
    stage = EffectivenessEstimator(robust_gains_default, OPTIONS, 1)
    fast, quiet = stage.N
    stage.N = [fast, 1.01 * quiet]
    with pytest.raises(VerificationFailed, match=r"vertex LMI #\d+ of eq. \(33\) fails"):
        stage.verify()
    mixed = fast.copy()
    mixed[0] = quiet[0] + (quiet[0] - fast[0]) * 50.0
    stage.N = [mixed, quiet]
    with pytest.raises(VerificationFailed, match=r"vertex LMI #\d+ of eq. \(33\) fails"):
        stage.verify()


def test_without_a_detected_step_the_estimates_are_those_without_the_jump_test(robust_gains_default):
    """The jump test changes nothing until it detects a step: on the slalom whose steering loses effectiveness at
    0.04 per second (a ramp, no step) it detects none, and every estimate equals the stage's without the test."""
    drive = simulate_plant([steer_loss_scenario()])
    y, u = drive.y[:, 0], drive.u[:, 0]
    out = []
    for options in (OPTIONS, OPTIONS.model_copy(update={"steer_jump_rad": 0.0})):
        estimator = EffectivenessObserver(robust_gains_default, options, y[:1], None, u[:1])
        steps = [estimator.step(y[k : k + 1], u[k : k + 1]) for k in range(len(drive.t))]
        out.append(np.array([np.concatenate([s.alpha[0], s.faults[0], s.bias[0], s.alpha_sigma[0]]) for s in steps]))
        jumps = estimator.stage.jumps
    assert OPTIONS.steer_jump_rad > 0.0 and jumps.tolist() == [[0, 0]]
    np.testing.assert_array_equal(out[0], out[1])


def test_the_jump_test_detects_steps_on_white_noise_at_its_design_rate(robust_gains_default):
    """The stage's jump test is a two-sided Page CUSUM whose threshold comes from its run length on white noise:
    designed for one detection per 1,000 samples (jump_false_alarm_interval_s 10 s at 100 Hz), fed 400 x 25,000
    standard normal innovations per channel, it detects 10,000 per channel within the tolerance."""
    options = OPTIONS.model_copy(update={"jump_false_alarm_interval_s": 10.0})
    rows, steps = 400, 25_000
    test = EffectivenessEstimator(robust_gains_default, options, rows).jump_test
    assert test.drift == JUMP_DRIFT and test.h == pytest.approx(cusum_threshold(JUMP_DRIFT, 1000.0))
    rng = np.random.default_rng(11)
    index, active = np.arange(rows), np.ones((rows, 2), dtype=bool)
    detected = np.zeros(2, dtype=np.int64)
    for _ in range(steps):
        detected += test.update(index, rng.standard_normal((rows, 2)), active)[1].sum(axis=0)
    assert detected / (rows * steps / 1000.0) == pytest.approx([1.0, 1.0], rel=PAGE_TEST_RATE_RTOL)


def test_a_step_is_attributed_to_the_bias_or_to_alpha_by_its_size_against_a_bias_steps():
    """attribute_step on a step d of the fitted fault, the state before it known to 0.1 mrad and alpha to 0.01, a
    bias step's standard deviation J = 2.5 mrad and odds of 1 in 100 for a loss: a 4 mrad step at a regressor of
    0.02 rad is the bias's (alpha stays within its sigma of 1); a 25 mrad step at 0.125 rad (10 J) is a loss to 0.8;
    an 8 mrad step at 0.03 rad is in between (a loss to 0.73 has about a fifth of the weight), and alpha's sigma
    carries that doubt."""
    J, bounds, log_odds = 0.0025, (-1.0, 0.5), float(np.log(0.01 / 0.99))
    P_0 = np.array([np.diag([1e-4**2, 0.01**2])] * 3)
    H = np.array([0.02, 0.125, 0.03])
    d = np.array([-0.004, -0.025, -0.008])
    par_end = np.stack([d, np.zeros(3)], axis=1)  # the bias followed the step
    par, P = attribute_step(par_end, P_0.copy(), H, np.zeros((3, 2)), P_0, np.full(3, J**2), bounds, log_odds)
    alpha, sigma = 1.0 + par[:, 1], np.sqrt(P[:, 1, 1])
    # the bias's: alpha moves by less than its sigma, the bias takes the step
    assert abs(alpha[0] - 1.0) < sigma[0] <= 0.01 and par[0, 0] == pytest.approx(d[0], abs=1e-4)
    # the loss's: alpha = 1 + d / H, the bias where it was, alpha's sigma that of the bias over H
    assert alpha[1] == pytest.approx(0.8, abs=1e-9) and par[1, 0] == 0.0 and sigma[1] < 0.011
    # in between: alpha between the two explanations, its sigma ten times either's
    assert 1.0 + d[2] / H[2] < alpha[2] < 1.0 - 0.02 and sigma[2] > 0.05

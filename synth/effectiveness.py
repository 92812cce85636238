"""Loss of effectiveness: each actuator's fault as a bias plus a share of its demand, f = b + (alpha - 1) u.

The paper's multiplicative fault (eqs. 9-11) is f = (alpha - 1) u_d. The
observer (eq. 19) estimates the fault as a random walk, which lags every
change of the demand: after a step of u the estimate follows (alpha - 1) u
through the observer's own error dynamics. This module estimates b and
alpha in a second stage that reads the observer and never feeds back into
it, so the observer, its gains and its certificate are exactly those of the
additive design:

1. **The observer's response to the demand.** For a fault equal to the
   demand, f_k = u_k, the error e = x_bar - x_hat of eq. (20) obeys

       eps_{k+1} = N(h_k) eps_k + D (u_{k+1} - u_k)

   with N(h_k) the blended transition the observer ran at k (its gain set,
   for a switched design) and D the fault rows (fault order 1: the fault is a
   random walk, its change the model's drift input). The reported fault then
   responds as H[u]_k = u_k - (eps_f - K_f C_bar eps)_k (K_f the output gain),
   so for f = b + theta u with b and theta = alpha - 1 slowly varying,

       f_hat_k = b + theta H[u]_k + (the observer's noise).

   H is the certified observer's own dynamics (uniformly exponentially
   stable at the certified rate), evaluated exactly on the measured premise
   each sample.
2. **A Kalman filter on that regression**, per actuator: the parameters
   [b, theta] are random walks (per-sample standard deviations
   ``bias_drift_share`` x sigma and ``effectiveness_rate_per_sqrt_s`` x sqrt(s)),
   the measurement is the observer's reported f_hat with the healthy
   estimate's RMS sigma as its noise. theta is told apart from b only by
   changes of the demand (with a constant demand the two are one number), so
   alpha_hat holds where the demand does not vary.
3. **Steps of the bias.** A lateral gust steps the steering fault estimate;
   the random walk of 2 says the bias moves slowly, so a step that meets a
   change of the demand is taken for a change of theta. Per channel with a
   jump size J > 0 (``torque_jump_nm``, ``steer_jump_rad``), a two-sided
   CUSUM (Page) on the filter's normalised innovation z = nu / sqrt(S),

       g+ = max(0, g+ + z - k),  g- = max(0, g- - z - k),  a step if max > h,

   k = :data:`JUMP_DRIFT`, h from the run length on white z
   (``jump_false_alarm_interval_s``; Brook and Evans, :mod:`synth.cusum`).
   After a detection the bias follows the estimate for ``jump_window_s``
   (process noise J^2 a sample: b takes the step while the observer delivers
   it). Then the step d = s_e - (b_0 + theta_0 H) of the fitted fault
   s_e = b + theta H is measured against the state one window before the
   test's evidence began (b_0, theta_0; its covariance P_0 aged by the random
   walks: the filter may have taken the step's start for a change of theta
   before the innovations showed it), and attributed by the likelihoods of two
   explanations: a bias step, d ~ N(0, J^2 + V_d), whose state is the Kalman
   update of P_0 + J^2 on b with s_e; or a loss, theta = theta_0 + d / H
   uniform within ``alpha_bounds`` (density 1 / ((theta_high - theta_low)
   |H|)), b = b_0, with prior probability ``jump_loss_prior``. An explanation
   with less than :data:`JUMP_PRUNE` of the posterior weight is dropped; the
   two are otherwise merged by their weights (the mixture's mean and
   covariance), so sigma_alpha carries the doubt between them. With no
   detection the filter is exactly that of 2.
4. **Reported**: alpha_hat = 1 + theta_hat (clipped to ``alpha_bounds``), the
   total fault f_hat + theta_hat (u - H[u]) (the observer's estimate with the
   lag of its demand-proportional part taken out: a bias still comes through
   at the observer's speed), and the bias b_hat = f_hat - theta_hat H[u].
5. **Certificate**: the recursion of 1 is the stage's only dynamics of its
   own. It is verified like every design (synth.certificate.verify) on the
   stage's own N_i of every gain set it holds, with the design's P(h) and R at
   rho = 0 (a point of the DMVT box, so within what the design certified):
   every vertex LMI of eq. (33) and the spectral radius of N(h) over the
   premise grid; any switching between the sets decays at the certified rate,
   as they share P(h). The filter of 2 and 3 is not part of it: its theta_hat is
   bounded by the clip to ``alpha_bounds``, not by a Lyapunov function.

The torque demand is T_d; the steering demand is the road-wheel angle the
actuator model gives for delta_d (its lag, as the observer carries it), so a
loss of steering effectiveness scales the angle the actuator delivers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from synth.augmented import N_FAULTS, N_STATES
from synth.certificate import Certificate, build_certificate, content_hash, merged, verify
from synth.cusum import PageTest
from synth.errors import BadParameters
from synth.gains import ObserverGains
from synth.model import FloatArray
from synth.observer import FuzzyObserver, StepResult
from synth.options import EffectivenessOptions
from synth.solver import SolveInfo

FAULTS = slice(N_STATES, N_STATES + N_FAULTS)
#: The estimator's per-row state of the bias-jump test.
JUMP_STATE = ("window", "history_par", "history_P", "rest_par", "rest_P", "rest_sample", "jumps")
#: Page's drift of the bias-jump test (module docstring, 3) [standard deviations of the normalised innovation]:
#: tuned for a shift of one.
JUMP_DRIFT = 0.5
#: An explanation of a detected step (bias or loss) with less than this posterior weight is dropped, as a Gaussian-sum
#: filter prunes its negligible components: a merged mixture with a distant, improbable mode has a wide alpha that
#: lets the next change of the demand move alpha_hat far.
JUMP_PRUNE = 0.05


@dataclass(slots=True)
class EffectivenessResult:
    """One sample of the second stage for a batch of nv vehicles.

    alpha : (nv, 2) estimated effectiveness of [torque, steering] [-]
    total : (nv, 2) estimated total fault b + (alpha - 1) u [N m, rad]
    bias : (nv, 2) estimated bias b [N m, rad]
    alpha_sigma : (nv, 2) the filter's posterior standard deviation of alpha, sqrt(P_theta_theta) [-]
    """

    alpha: FloatArray
    total: FloatArray
    bias: FloatArray
    alpha_sigma: FloatArray


class EffectivenessEstimator:
    """The second stage for a batch of vehicles sharing one design (module docstring), one row each.

    Call :meth:`step` after each observer step of the whole batch with that step's result and the same y, u;
    or :meth:`step_rows` for any subset of rows (the service steps the vehicles of a tick). Each row keeps its
    own state, start delay and previous sample; :meth:`reset` starts rows afresh, :meth:`grow` adds rows.
    """

    def __init__(
        self, gains: ObserverGains, options: EffectivenessOptions, nv: int, u0: ArrayLike | None = None
    ) -> None:
        if gains.options.fault_order != 1:
            raise BadParameters(
                f"the effectiveness stage needs a design of fault order 1 (a random-walk fault), "
                f"got {gains.options.fault_order}"
            )
        if np.any(gains.E) or not np.allclose(gains.M, np.eye(gains.M.shape[0])):
            raise BadParameters("the effectiveness stage needs a design with E = 0 and M = I (the 'robust' designs)")
        self.gains = gains
        self.options = options
        aug = gains.model
        self.nts = aug.nts
        n = aug.n
        self.n = n
        self.C = aug.C_bar
        self.sets = [gains] if gains.quiet is None else [gains, gains.quiet_gains()]
        #: per gain set: N_i (r, n, n) and the reported fault rows' map of the error, I_f - K_f C (2, n)
        self.N = [g.N for g in self.sets]
        self.report = [np.eye(n)[FAULTS] - g.output_gain[FAULTS] @ self.C for g in self.sets]
        s = gains.params.sample_period_s
        self.steer_lag = gains.params.steer_lag_factor
        self.steer_lag_mean = gains.params.steer_lag_mean_factor
        sigma = np.array([options.torque_sigma_nm, options.steer_sigma_rad])
        self.sigma = sigma
        self.R = sigma**2
        self.Q = np.stack(
            [
                np.diag([(options.bias_drift_share * sg) ** 2, options.effectiveness_rate_per_sqrt_s**2 * s])
                for sg in sigma
            ]
        )
        self.start_samples = round(options.start_after_s / s)
        self.theta_low, self.theta_high = options.alpha_bounds[0] - 1.0, options.alpha_bounds[1] - 1.0
        #: the bias-jump test (module docstring, 3): per channel the jump variance J^2, on where J > 0
        self.jump_var = np.array([options.torque_jump_nm, options.steer_jump_rad]) ** 2
        self.jump_on = self.jump_var > 0.0
        self.jump_test = PageTest(nv, 2, JUMP_DRIFT, options.jump_false_alarm_interval_s / s)
        self.window_samples = max(1, round(options.jump_window_s / s))
        self.loss_log_odds = float(np.log(options.jump_loss_prior / (1.0 - options.jump_loss_prior)))
        self.steer_state = np.zeros(nv)
        self.eps = np.zeros((nv, n, 2))
        #: each row's previous transition and regressor; primed: the row has a previous sample
        self.N_prev = np.zeros((nv, n, n))
        self.u_prev = np.zeros((nv, 2))
        self.primed = np.zeros(nv, dtype=bool)
        #: per vehicle and channel: [b, theta] and their covariance
        self.par = np.zeros((nv, 2, 2))
        self.P = np.zeros((nv, 2, 2, 2))
        self.samples = np.zeros(nv, dtype=np.int64)
        #: per vehicle and channel: the samples left of the window in which the bias follows a detected step, the
        #: states of the last window_samples updates (a ring), the state a step is measured from (one window before
        #: the jump test's evidence began) and its update, and the steps detected since the row started
        self.window = np.zeros((nv, 2), dtype=np.int64)
        self.history_par = np.zeros((nv, self.window_samples, 2, 2))
        self.history_P = np.zeros((nv, self.window_samples, 2, 2, 2))
        self.rest_par = np.zeros((nv, 2, 2))
        self.rest_P = np.zeros((nv, 2, 2, 2))
        self.rest_sample = np.zeros((nv, 2), dtype=np.int64)
        self.jumps = np.zeros((nv, 2), dtype=np.int64)
        self.reset(np.arange(nv), u0)
        #: the stage's own recursion, verified (module docstring, 5); VerificationFailed here otherwise
        self.certificate = self.verify()

    def verify(self) -> Certificate:
        """Verify the stage's recursion eps_{k+1} = N(h_k) eps_k on its own N_i (module docstring, 5).

        Returns
        -------
        Certificate
            Design ``"<design>+effectiveness"``: the decay rate certified for the recursion, the minimum
            eigenvalue of every vertex LMI of eq. (33) at rho = 0 (both gain sets of a switched design), the
            spectral radius of N(h) over the premise grid, and the content hash of the stage's N_i and
            reported-fault maps with the design's hash.

        Raises
        ------
        VerificationFailed
            A check fails: the message names the first that does.
        """
        started = time.perf_counter()
        design = self.gains.certificate
        g = self.gains
        reports = [verify(self.nts, (), g.P, g.R, design.requested_decay_rate, N, g.M, g.T) for N in self.N]
        report = reports[0] if len(reports) == 1 else merged(*reports)
        solved = SolveInfo(design.solver, design.solver_status, design.solver_iterations, 0.0, 0.0, 0.0)
        stage_hash = content_hash(
            {"N": np.stack(self.N), "report": np.stack(self.report)},
            {"design": design.content_hash, "stage": "effectiveness"},
        )
        certificate = build_certificate(
            g.options,
            report,
            solved,
            lmi_form="vertex",
            alpha=design.requested_decay_rate,
            n_lmis_solved=0,
            solves=0,
            timings={"verify": time.perf_counter() - started},
            gains_hash=stage_hash,
            symmetry="none",
            notes=[
                "the effectiveness stage's recursion eps_{k+1} = N(h_k) eps_k, verified with the design's P(h) and "
                "R at rho = 0 (solver: the design's, which found them)",
                "not covered: the Kalman filter of [b, theta], whose alpha_hat is clipped to alpha_bounds",
            ],
        )
        return replace(certificate, design=f"{design.design}+effectiveness")

    @property
    def n_rows(self) -> int:
        return len(self.samples)

    def reset(self, rows: np.ndarray, u0: ArrayLike | None = None) -> None:
        """Start ``rows`` afresh (alpha 1, no bias, the start delay again), their steering actuator at u0's angle."""
        u = np.zeros((len(rows), 2)) if u0 is None else np.atleast_2d(np.asarray(u0, dtype=float))
        self.steer_state[rows] = u[:, 1]
        self.eps[rows] = 0.0
        self.primed[rows] = False
        self.par[rows] = 0.0
        self.P[rows] = 0.0
        self.P[rows, :, 0, 0] = (10.0 * self.sigma) ** 2
        self.P[rows, :, 1, 1] = self.options.initial_alpha_sigma**2
        self.samples[rows] = 0
        self.jump_test.reset(rows)
        self.window[rows] = 0
        self.history_par[rows] = 0.0
        self.history_P[rows] = 0.0
        self.rest_par[rows] = 0.0
        self.rest_P[rows] = 0.0
        self.rest_sample[rows] = 0
        self.jumps[rows] = 0

    def grow(self, nv: int) -> None:
        """Room for ``nv`` rows; the new ones start afresh."""
        extra = nv - self.n_rows
        if extra <= 0:
            return
        old = self.n_rows
        for name in (*("steer_state", "eps", "N_prev", "u_prev", "primed", "par", "P", "samples"), *JUMP_STATE):
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, np.zeros((extra, *a.shape[1:]), dtype=a.dtype)]))
        self.jump_test.grow(nv)
        self.reset(np.arange(old, nv))

    def regressor(self, rows: np.ndarray, u: FloatArray) -> FloatArray:
        """The demand each fault is a share of, (k, 2): T_d, and the actuator model's angle over the sample."""
        out = u.copy()
        if self.steer_lag != 0.0:
            state = self.steer_state[rows]
            out[:, 1] = state + self.steer_lag_mean * (u[:, 1] - state)
            self.steer_state[rows] = self.steer_lag * state + (1.0 - self.steer_lag) * u[:, 1]
        return out

    def step(self, result: StepResult, y: ArrayLike, u: ArrayLike) -> EffectivenessResult:
        """The estimates at k from the observer's result at k and the sample's y_k, u_k (nv, 2) each."""
        return self.step_rows(np.arange(self.n_rows), result.faults, result.fast, y, u)

    def step_rows(
        self, rows: np.ndarray, f_hat: FloatArray, fast: np.ndarray | None, y: ArrayLike, u: ArrayLike
    ) -> EffectivenessResult:
        """The estimates at k of ``rows`` (distinct) from the observer's reported faults f_hat (k, 2) at k, the
        gain set each row ran (``fast``; None for one set) and the sample's y_k, u_k (k, 2) each."""
        y = np.atleast_2d(np.asarray(y, dtype=float))
        u_d = self.regressor(rows, np.atleast_2d(np.asarray(u, dtype=float)))
        eps = self.eps[rows]
        primed = self.primed[rows]
        if primed.any():
            # eps_k = N_{k-1} eps_{k-1} + D (u_k - u_{k-1})
            p = np.flatnonzero(primed)
            e = np.einsum("vjk,vkc->vjc", self.N_prev[rows[p]], eps[p])
            du = u_d[p] - self.u_prev[rows[p]]
            e[:, N_STATES, 0] += du[:, 0]
            e[:, N_STATES + 1, 1] += du[:, 1]
            eps[p] = e
        # this sample's transition and reported-fault map: the gain set the observer ran
        xi = self.nts.clip_premise(self.nts.premise(y[:, 0], y[:, 1]))
        h = self.nts.memberships(xi)
        if len(self.sets) == 1 or fast is None:
            N, report = np.einsum("vi,ijk->vjk", h, self.N[0]), np.broadcast_to(self.report[0], (h.shape[0], 2, self.n))
        else:
            pick = np.asarray(fast, dtype=bool)[:, None, None]
            N = np.where(pick, np.einsum("vi,ijk->vjk", h, self.N[0]), np.einsum("vi,ijk->vjk", h, self.N[1]))
            report = np.where(pick, self.report[0][None], self.report[1][None])
        # H[u]_k = u_k - (I_f - K_f C) eps_k, per channel (its own column)
        response = np.einsum("vfj,vjc->vfc", report, eps)
        H = u_d - np.stack([response[:, 0, 0], response[:, 1, 1]], axis=1)
        started = self.samples[rows] >= self.start_samples
        if started.all():
            self._update(rows, f_hat, H)
        elif started.any():
            self._update(rows[started], f_hat[started], H[started])
        self.samples[rows] += 1
        self.eps[rows] = eps
        self.N_prev[rows] = N
        self.u_prev[rows] = u_d
        self.primed[rows] = True
        theta = self.par[rows, :, 1]
        bias = f_hat - theta * H
        total = f_hat + theta * (u_d - H)
        return EffectivenessResult(alpha=1.0 + theta, total=total, bias=bias, alpha_sigma=self.alpha_sigma(rows))

    def alpha_sigma(self, rows: np.ndarray) -> FloatArray:
        """The posterior standard deviation of alpha_hat of ``rows``, (k, 2) [-]: sqrt(P_theta_theta) of each
        channel's filter (the prior ``initial_alpha_sigma`` until the row's stage starts). It grows while the
        demand holds still (theta unobservable) and shrinks with the demand's changes (docs/math.md section 14)."""
        return np.sqrt(self.P[rows, :, 1, 1])

    def _update(self, rows: np.ndarray, f_hat: FloatArray, H: FloatArray) -> None:
        """One Kalman step per channel of [b, theta] with the measurement f_hat = b + theta H, and the bias-jump
        test on its innovation (module docstring, 3)."""
        phi = np.stack([np.ones_like(H), H], axis=2)  # (k, 2 channels, 2)
        P = self.P[rows] + self.Q[None]
        P_phi = np.einsum("vcij,vcj->vci", P, phi)
        S = np.einsum("vci,vci->vc", phi, P_phi) + self.R[None]
        par = self.par[rows]
        innovation = f_hat - np.einsum("vci,vci->vc", phi, par)
        following = None
        if self.jump_on.any():
            following = self._test(rows, innovation / np.sqrt(S))
            slot = self.samples[rows] % self.window_samples
            self.history_par[rows, slot], self.history_P[rows, slot] = par, self.P[rows]
        if following is not None and following.any():
            # in a window the bias follows the estimate: its process noise J^2 a sample (P phi and S with it)
            free = np.where(following, self.jump_var[None], 0.0)
            P[:, :, 0, 0] += free
            P_phi[:, :, 0] += free
            S = S + free
        G = P_phi / S[:, :, None]
        par = par + G * innovation[:, :, None]
        P = P - G[:, :, :, None] * P_phi[:, :, None, :]
        self.P[rows] = 0.5 * (P + np.swapaxes(P, 2, 3))
        par[:, :, 1] = np.clip(par[:, :, 1], self.theta_low, self.theta_high)
        self.par[rows] = par
        if following is not None and following.any():
            self._close_windows(rows, following, H)

    def _test(self, rows: np.ndarray, z: FloatArray) -> np.ndarray:
        """The jump test on the normalised innovations z (k, 2) of ``rows`` outside a window, before their update:
        where its evidence begins, the state one window before is kept as the one a step is measured from; a
        detection opens a window. Returns where the bias follows the estimate this sample, (k, 2) bool."""
        window = self.window[rows]
        began, jump = self.jump_test.update(rows, z, (window == 0) & self.jump_on[None])
        i, c = np.nonzero(began)
        if len(i):
            # the state one window before: the filter may have taken the step's start for a change of theta
            r = rows[i]
            updates = self.samples[r] - self.start_samples
            full = updates >= self.window_samples
            slot = self.samples[r] % self.window_samples
            self.rest_par[r, c] = np.where(full[:, None], self.history_par[r, slot, c], self.par[r, c])
            self.rest_P[r, c] = np.where(full[:, None, None], self.history_P[r, slot, c], self.P[r, c])
            self.rest_sample[r, c] = self.samples[r] - np.where(full, self.window_samples, 0)
        if jump.any():
            window = window + np.where(jump, self.window_samples, 0)
            self.window[rows] = window
            self.jumps[rows] += jump
        return np.asarray(window > 0)

    def _close_windows(self, rows: np.ndarray, following: np.ndarray, H: FloatArray) -> None:
        """Count the windows down and attribute the step of those that end (module docstring, 3), from the state
        kept one window before the evidence began, aged by the random walks to now."""
        window = self.window[rows] - following
        self.window[rows] = window
        i, c = np.nonzero(following & (window == 0))
        if not len(i):
            return
        r = rows[i]
        age = (self.samples[r] - self.rest_sample[r, c] + 1).astype(float)
        P_0 = self.rest_P[r, c] + age[:, None, None] * self.Q[c]
        theta_bounds = (self.theta_low, self.theta_high)
        par, P = attribute_step(
            self.par[r, c], self.P[r, c], H[i, c], self.rest_par[r, c], P_0, self.jump_var[c], theta_bounds,
            self.loss_log_odds,
        )  # fmt: skip
        self.par[r, c], self.P[r, c] = par, P


def attribute_step(
    par: FloatArray,
    P: FloatArray,
    H: FloatArray,
    par_0: FloatArray,
    P_0: FloatArray,
    jump_var: FloatArray,
    theta_bounds: tuple[float, float],
    loss_log_odds: float,
    prune: float = JUMP_PRUNE,
) -> tuple[FloatArray, FloatArray]:
    """A detected step of the fault attributed to the bias or to the effectiveness (module docstring, 3).

    Parameters
    ----------
    par, P : (m, 2), (m, 2, 2)
        [b, theta] and their covariance at the window's end (the bias followed the step).
    H : (m,)
        The regressor at the window's end [N m or rad].
    par_0, P_0 : (m, 2), (m, 2, 2)
        [b, theta] one window before the jump test's evidence began, their covariance aged to now by the random
        walks.
    jump_var : (m,)
        J^2, the variance of a step of the bias [N m^2 or rad^2].
    theta_bounds : (low, high)
        A loss puts theta uniformly within these [-].
    loss_log_odds : float
        ln(p / (1 - p)), p the prior probability that a step is a loss.
    prune : float
        An explanation with less posterior weight than this is dropped.

    Returns
    -------
    par, P : (m, 2), (m, 2, 2)
        The two explanations merged by their posterior weights (the mixture's mean and covariance).
    """
    phi = np.stack([np.ones_like(H), H], axis=1)
    # s_e = b + theta H, the fitted fault; d = s_e - (b_0 + theta_0 H), the step
    fitted = np.einsum("mi,mi->m", phi, par)
    fitted_var = np.einsum("mi,mij,mj->m", phi, P, phi)
    step = fitted - np.einsum("mi,mi->m", phi, par_0)
    bias_var = jump_var + fitted_var + np.einsum("mi,mij,mj->m", phi, P_0, phi)
    # a bias step: d ~ N(0, J^2 + V_d); a loss: theta uniform within its bounds, d = (theta - theta_0) H
    log_bias = -0.5 * (step**2 / bias_var + np.log(2.0 * np.pi * bias_var))
    H_safe = np.where(H == 0.0, 1.0, H)
    theta = par_0[:, 1] + step / H_safe
    possible = (H != 0.0) & (theta >= theta_bounds[0]) & (theta <= theta_bounds[1])
    log_loss = -np.log((theta_bounds[1] - theta_bounds[0]) * np.abs(H_safe))
    log_odds = np.clip(log_loss - log_bias + loss_log_odds, -700.0, 700.0)
    w = np.where(possible, 1.0 / (1.0 + np.exp(-log_odds)), 0.0)
    w = np.where(w < prune, 0.0, np.where(w > 1.0 - prune, 1.0, w))
    # the bias stepped: the Kalman update of P_0 + J^2 on b with the measurement s_e (its variance V_se)
    prior = P_0.copy()
    prior[:, 0, 0] += jump_var
    gain = np.einsum("mij,mj->mi", prior, phi) / bias_var[:, None]
    mean_b = par_0 + gain * step[:, None]
    mean_b[:, 1] = np.clip(mean_b[:, 1], *theta_bounds)
    cov_b = prior - gain[:, :, None] * np.einsum("mi,mij->mj", phi, prior)[:, None, :]
    b_var = P_0[:, 0, 0]
    # a loss: b = b_0, theta = (s_e - b_0) / H
    mean_t = np.stack([par_0[:, 0], np.where(possible, theta, par_0[:, 1])], axis=1)
    cov_t = _sym(b_var, -b_var / H_safe, (fitted_var + b_var) / H_safe**2)
    mean = (1.0 - w)[:, None] * mean_b + w[:, None] * mean_t
    d_b, d_t = mean_b - mean, mean_t - mean
    cov = (1.0 - w)[:, None, None] * (cov_b + d_b[:, :, None] * d_b[:, None, :]) + w[:, None, None] * (
        cov_t + d_t[:, :, None] * d_t[:, None, :]
    )
    return mean, cov


def _sym(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    """(m, 2, 2) symmetric matrices [[a, b], [b, c]]."""
    return np.stack([np.stack([a, b], axis=1), np.stack([b, c], axis=1)], axis=1)


@dataclass(slots=True)
class EffectivenessStep:
    """One step of :class:`EffectivenessObserver` for a batch: the observer's result with the total faults.

    x_hat : (nv, n) the observer's reported estimate, its fault rows replaced by the total faults
    in_domain, certified : (nv,) as the observer's; alpha, bias, alpha_sigma : (nv, 2) as :class:`EffectivenessResult`;
    observer_faults : (nv, 2) the observer's own (additive) fault estimate
    """

    x_hat: FloatArray
    in_domain: np.ndarray
    alpha: FloatArray
    bias: FloatArray
    observer_faults: FloatArray
    alpha_sigma: FloatArray
    #: (nv,) as the observer's :attr:`~synth.observer.StepResult.certified`
    certified: np.ndarray

    @property
    def state(self) -> FloatArray:
        """(nv, 3) estimated [v_x, v_y, r]."""
        return self.x_hat[:, :3]

    @property
    def faults(self) -> FloatArray:
        """(nv, 2) estimated total faults [T_f [N m], delta_f [rad]]: bias plus (alpha - 1) demand."""
        return self.x_hat[:, FAULTS]


class EffectivenessObserver:
    """A :class:`~synth.observer.FuzzyObserver` and its :class:`EffectivenessEstimator`, stepped together."""

    def __init__(
        self,
        gains: ObserverGains,
        options: EffectivenessOptions,
        y0: ArrayLike,
        x_hat0: ArrayLike | None = None,
        u0: ArrayLike | None = None,
    ) -> None:
        self.observer = FuzzyObserver(gains, y0, x_hat0, u0)
        self.stage = EffectivenessEstimator(gains, options, self.observer.n_vehicles, u0)

    def step(self, y: ArrayLike, u: ArrayLike, stage_u: ArrayLike | None = None) -> EffectivenessStep:
        """One observer step, then the loss-of-effectiveness stage on its fault estimates.

        Parameters
        ----------
        y, u : (nv, 2) array_like
            Sample k's measured [v_x, r] and demanded [T_d, delta_d], in the units of
            :meth:`~synth.observer.FuzzyObserver.step`.
        stage_u : (nv, 2) array_like, optional
            The demand the stage regresses on, where it is not the observer's ``u``: on a road grade the observer
            takes the level-ground torque and the stage the demanded one (synth.model.model_inputs).

        Returns
        -------
        EffectivenessStep
            The total faults with alpha, bias and the observer's own estimate.
        """
        result = self.observer.step(y, u)
        second = self.stage.step(result, y, u if stage_u is None else stage_u)
        x_hat = np.array(result.x_hat, dtype=float)
        x_hat[:, FAULTS] = second.total
        return EffectivenessStep(
            x_hat=x_hat,
            in_domain=result.in_domain,
            alpha=second.alpha,
            bias=second.bias,
            observer_faults=np.array(result.faults, dtype=float),
            alpha_sigma=second.alpha_sigma,
            certified=result.certified,
        )

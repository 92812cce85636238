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
3. **Reported**: alpha_hat = 1 + theta_hat (clipped to ``alpha_bounds``), the
   total fault f_hat + theta_hat (u - H[u]) (the observer's estimate with the
   lag of its demand-proportional part taken out: a bias still comes through
   at the observer's speed), and the bias b_hat = f_hat - theta_hat H[u].
4. **Certificate**: the recursion of 1 is the stage's only dynamics of its
   own. It is verified like every design (synth.certificate.verify) on the
   stage's own N_i of every gain set it holds, with the design's P(h) and R at
   rho = 0 (a point of the DMVT box, so within what the design certified):
   every vertex LMI of eq. (33) and the spectral radius of N(h) over the
   premise grid; any switching between the sets decays at the certified rate,
   as they share P(h). The filter of 2 is not part of it: its theta_hat is
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
from synth.errors import BadParameters
from synth.gains import ObserverGains
from synth.model import FloatArray
from synth.observer import FuzzyObserver, StepResult
from synth.options import EffectivenessOptions
from synth.solver import SolveInfo

FAULTS = slice(N_STATES, N_STATES + N_FAULTS)


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
        self.reset(np.arange(nv), u0)
        #: the stage's own recursion, verified (module docstring, 4); VerificationFailed here otherwise
        self.certificate = self.verify()

    def verify(self) -> Certificate:
        """Verify the stage's recursion eps_{k+1} = N(h_k) eps_k on its own N_i (module docstring, 4).

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

    def grow(self, nv: int) -> None:
        """Room for ``nv`` rows; the new ones start afresh."""
        extra = nv - self.n_rows
        if extra <= 0:
            return
        old = self.n_rows
        for name in ("steer_state", "eps", "N_prev", "u_prev", "primed", "par", "P", "samples"):
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, np.zeros((extra, *a.shape[1:]), dtype=a.dtype)]))
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
        """One Kalman step per channel of [b, theta] with the measurement f_hat = b + theta H."""
        phi = np.stack([np.ones_like(H), H], axis=2)  # (k, 2 channels, 2)
        P = self.P[rows] + self.Q[None]
        P_phi = np.einsum("vcij,vcj->vci", P, phi)
        S = np.einsum("vci,vci->vc", phi, P_phi) + self.R[None]
        G = P_phi / S[:, :, None]
        par = self.par[rows]
        innovation = f_hat - np.einsum("vci,vci->vc", phi, par)
        par = par + G * innovation[:, :, None]
        P = P - G[:, :, :, None] * P_phi[:, :, None, :]
        self.P[rows] = 0.5 * (P + np.swapaxes(P, 2, 3))
        par[:, :, 1] = np.clip(par[:, :, 1], self.theta_low, self.theta_high)
        self.par[rows] = par


@dataclass(slots=True)
class EffectivenessStep:
    """One step of :class:`EffectivenessObserver` for a batch: the observer's result with the total faults.

    x_hat : (nv, n) the observer's reported estimate, its fault rows replaced by the total faults
    in_domain : (nv,) as the observer's; alpha, bias, alpha_sigma : (nv, 2) as :class:`EffectivenessResult`;
    observer_faults : (nv, 2) the observer's own (additive) fault estimate
    """

    x_hat: FloatArray
    in_domain: np.ndarray
    alpha: FloatArray
    bias: FloatArray
    observer_faults: FloatArray
    alpha_sigma: FloatArray

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

    def step(self, y: ArrayLike, u: ArrayLike) -> EffectivenessStep:
        """One observer step, then the loss-of-effectiveness stage on its fault estimates.

        Parameters
        ----------
        y, u : (nv, 2) array_like
            Sample k's measured [v_x, r] and demanded [T_d, delta_d], in the units of
            :meth:`~synth.observer.FuzzyObserver.step`.

        Returns
        -------
        EffectivenessStep
            The total faults with alpha, bias and the observer's own estimate.
        """
        result = self.observer.step(y, u)
        second = self.stage.step(result, y, u)
        x_hat = np.array(result.x_hat, dtype=float)
        x_hat[:, FAULTS] = second.total
        return EffectivenessStep(
            x_hat=x_hat,
            in_domain=result.in_domain,
            alpha=second.alpha,
            bias=second.bias,
            observer_faults=np.array(result.faults, dtype=float),
            alpha_sigma=second.alpha_sigma,
        )

"""The runtime fuzzy observer (Algorithm 1), vectorised over a batch of vehicles.

For every vehicle of the batch, at sample k:

    x_hat_k = z_k - E y_k                                                (19)
    z_{k+1} = N(h_k) z_k + L(h_k) y_k + M T1 (g(xi_k) + B u_k) + M G_bar phi(x_hat_k)

with h_k = h(xi_k), xi_k = [1/v_x, r] from the measured y_k. Departures from
the letter of Algorithm 1, each keeping the certificate meaningful:

* the premise is clipped to the design box before h and g are evaluated, and
  ``in_domain`` flags the vehicles whose measured premise left it;
* the reported estimate is x_hat_k + K (y_k - C_bar x_hat_k), with the output
  gain K of the robust design (synth.robust): the faults filtered with the
  current measurement, as an EKF reports x_{k|k}. K = 0 for the paper's
  designs. It is an output map only: the observer state and its certified
  error dynamics are those of eq. (19);
* phi is evaluated at v_y_hat saturated to [v_y,min, v_y,max]. For a true v_y
  inside the bounds, phi(v_y) - phi(sat(v_y_hat)) = rho_eff (v_y - v_y_hat)
  with rho_eff = (v_y + sat(v_y_hat)) * (v_y - sat(v_y_hat)) / (v_y - v_y_hat)
  in the convex hull S_rho (the saturation is 1-Lipschitz and moves towards
  v_y), so the DMVT bound of eq. (26) holds even when the estimate strays.
  The cornering drag phi_c (synth.fuzzy) is evaluated the same way, at the
  saturated v_y_hat and the applied steering angle delta_d + b_delta delta_f_hat
  saturated to its bound.

A switched design (``DesignOptions.switching``) has a fast and a quiet gain
set under one Lyapunov function; :func:`switched_step` picks one per vehicle
and sample from an exponentially weighted statistic of the normalised
innovation (synth.options.SwitchingRule). Any switching sequence keeps the
certified decay rate.

One implementation serves the replay tool, the simulators and the cloud
service: :func:`observer_step` and :func:`switched_step` are stateless,
:class:`FuzzyObserver` keeps the state of a fixed batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from synth.augmented import N_STATES, VY_INDEX, AugmentedEstimate, front_force_bound_n
from synth.errors import BadParameters, check_shape
from synth.fuzzy import RULE_CORNERS
from synth.gains import ObserverGains
from synth.model import FloatArray, model_demand
from synth.options import SwitchingRule

#: Index of the steering fault delta_f (at sample k) in the augmented state.
STEER_FAULT_INDEX = N_STATES + 1
#: The measured nonlinear consequent g(xi) of eq. (15) is linear in these monomials of (v_x, r).
G_FEATURES = ("v_x^2", "r/v_x", "v_x r")


def g_feature_matrix(gains: ObserverGains) -> FloatArray:
    """The monomial map of the measured consequent g of eq. (15) (corrected).

    Parameters
    ----------
    gains : ObserverGains
        The gains whose vehicle and sample period define g.

    Returns
    -------
    (3, 3) ndarray
        K with g(v_x, r) = K @ [v_x^2, r / v_x, v_x r] + g_0 (g_0 of :func:`g_constant`).
    """
    k = gains.params.symbols()
    s = k["s"]
    K = np.zeros((3, 3))
    K[0, 0] = -s * k["C_x"] / k["m_eff"]  # g_1 = -s (C_x v_x^2 + F_r) / m_eff, v_x^2 part
    K[1, 1] = s * 2.0 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / k["M_v"]  # g_2, r/v_x part
    K[1, 2] = -s  # g_2, -s v_x r part
    K[2, 1] = -s * 2.0 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / k["I_z"]  # g_3
    return K


def g_constant(gains: ObserverGains) -> FloatArray:
    """The constant part of g: the rolling resistance, g_0 = [-s F_r / m_eff, 0, 0].

    Parameters
    ----------
    gains : ObserverGains
        Their vehicle's F_r [N] and m_eff [kg], and the sample period s [s].

    Returns
    -------
    (3,) ndarray
        g_0 [m/s].
    """
    k = gains.params.symbols()
    return np.array([-k["s"] * k["F_r"] / k["m_eff"], 0.0, 0.0])


@dataclass(frozen=True)
class RuntimeGains:
    """Gains stacked for the batched step: z_{k+1}^T = W^T Phi with one feature column per vehicle.

    The memberships of eq. (16) are products of two sector weights, a = a_0 + a_1 V_x and
    b = b_0 + b_1 r: h = [a b, a (1 - b), (1 - a) b, (1 - a)(1 - b)]. Any rule blend is therefore
    bilinear in the (clipped) premise:

        sum_i h_i W_i = W_4 + a (W_2 - W_4) + b (W_3 - W_4) + a b (W_1 - W_2 - W_3 + W_4)
                      = Q_0 + V_x Q_V + r Q_r + V_x r Q_Vr.

    With x = [y; z] per vehicle and Q_i = [L_i, N_i]^T:

    Phi = [x; V_x x'; r x'; V_x r x'; v_x^2; r/v_x; v_x r; u; phi; (1); (phi_c)]  (n + 2 + 3 m + 6 [+ 2], nv)
    W   = [Q_0; Q_V'; Q_r'; Q_Vr'; (M T1 K)^T; (M T1 B)^T; (M G_bar)^T; (M T1 g_0)^T; (M G_c_bar)^T]

    so the whole of Algorithm 1, line 9, is a few broadcast products and one GEMM. x' = x[:m] is
    the part of x the premise acts on: the rows of Q_V, Q_r and Q_Vr below m are zero in every gain
    set (the fault states enter through constant matrices, so the blend never multiplies them), and
    leaving them out of Phi saves their products, their share of the GEMM and of the memory it
    reads. What depends on x alone comes from a second, small GEMM X^T x: with an output gain K
    (robust design), the reported estimate x_hat + K (y - C_bar x_hat) = (I - K C_bar)(z - E y) + K y;
    for a switched design, also the innovation (y - C_bar x_hat), scaled so that its squared norm
    is the switching statistic's increment. Folding them into W would multiply their zero columns
    against the other rows of Phi.

    The last two rows exist only for the profiles that need them: a constant 1 for the rolling
    resistance, and the cornering drag phi_c = F_yf sin(delta) evaluated at the estimates
    (synth.fuzzy.NTSModel.phi_c), so the paper's profile keeps the paper's step and its cost.
    """

    gains: ObserverGains
    #: (n, n + 2 + 3 m + 6): z_{k+1} = WT Phi
    WT: FloatArray
    #: (len(K_rows) [+ 2 for a switched design], n + 2): the reported estimate [and the innovation] = XT x
    XT: FloatArray
    #: the leading rows of x = [y; z] that the premise multiplies (x' of the class docstring)
    m: int
    E: FloatArray
    E_is_zero: bool
    #: rows of the reported estimate that come from XT: all n when the design has an output gain, none otherwise
    K_rows: np.ndarray
    n: int
    n_rules: int
    premise_low: FloatArray
    premise_high: FloatArray
    vy_low: float
    vy_high: float
    #: (2, 1) the design box in measured terms, [v_x, r] low and high: the clip of the premise
    measured_low: FloatArray
    measured_high: FloatArray
    #: a switched design's quiet set (rows as WT, XT) and both sets stacked; None for one gain set. XT_pair
    #: holds the quiet set's reported rows and the innovation (the same in both sets), then the fast set's
    #: reported rows ``fast_rows``: those that differ from the quiet set's (the fault rows, where the output
    #: gains differ), the only ones a mixed batch must pick per vehicle
    WT_quiet: FloatArray | None = None
    WT_pair: FloatArray | None = None
    XT_quiet: FloatArray | None = None
    XT_pair: FloatArray | None = None
    fast_rows: slice = field(default_factory=lambda: slice(0, 0))
    #: the switching rule (synth.options.SwitchingRule) in samples; the innovation rows of XT carry
    #: the statistic's weight sqrt((1 - lambda) / 2) / sigma
    switch_threshold: float = np.inf
    switch_forgetting: float = 0.0
    hold_samples: int = 0
    start_samples: int = 0
    #: rows of Phi after phi: 1 with a rolling resistance, phi_c with the cornering drag
    rolling: bool = False
    cornering: bool = False
    #: the cornering drag's constants: 2 C_f [N/rad], l_f [m], b_delta, the bound of |delta| [rad]
    two_C_f: float = 0.0
    l_f: float = 0.0
    b_delta: float = 1.0
    steer_max: float = np.inf
    #: the bound of |F_yf| the estimate is saturated to [N] (synth.augmented.front_force_bound_n)
    front_force_max: float = np.inf
    #: a = exp(-s / tau_delta) of the steering actuator's lag (VehicleParams.steer_lag_factor); 0: ideal actuator.
    #: With a lag, z carries one more column: the model's road-wheel angle, the lagged demand
    steer_lag: float = 0.0
    #: c of the actuator's mean angle over a sample, delta_k + c (delta_d,k - delta_k) (steer_lag_mean_factor)
    steer_lag_mean: float = 1.0
    #: the model's steering input carries the load transfer's angle (cg_height_m, synth.model.model_demand)
    load_transfer: bool = False

    @property
    def state_size(self) -> int:
        """Columns of an observer state z: the n of eq. (19), and the actuator model's angle with a lag."""
        return self.n + (1 if self.steer_lag != 0.0 else 0)

    @property
    def n_features(self) -> int:
        """Rows of Phi: [x; V_x x'; r x'; V_x r x'; v_x^2; r/v_x; v_x r; u; phi; (1); (phi_c)]."""
        return self.n + 2 + 3 * self.m + 6 + int(self.rolling) + int(self.cornering)

    @classmethod
    def from_gains(cls, gains: ObserverGains) -> RuntimeGains:
        """The runtime form of ``gains``: stacked, transposed feature weights for one GEMM per step.

        Parameters
        ----------
        gains : ObserverGains
            Verified gains of the 4-rule model.

        Returns
        -------
        RuntimeGains

        Raises
        ------
        BadParameters
            The gains do not have the 4 rules of eq. (16).
        """
        aug = gains.model
        r, n, _ = gains.N.shape
        if r != len(RULE_CORNERS):
            raise BadParameters(f"the runtime step needs the {len(RULE_CORNERS)} rules of eq. (16), got {r}")
        rule = gains.options.switching
        quiet = gains.quiet_gains() if gains.quiet is not None and rule is not None else None
        sets = [gains] if quiet is None or rule is None else [gains, quiet]
        # every row of the reported estimate out of the small GEMM (no copy of the rest) when a set has an output gain
        K_rows = np.arange(n) if any(np.any(g.output_gain) for g in sets) else np.arange(0)
        innovation_scale = _innovation_scale(gains) if rule is not None and len(sets) == 2 else None
        stacked = [_stacked_gains(g, K_rows, innovation_scale) for g in sets]
        m = _blended_rows([W for W, _ in stacked], n)
        n2 = n + 2
        rolling, cornering = gains.params.rolling_resistance_n != 0.0, aug.nts.has_cornering_drag
        n_tail = 6 + int(rolling) + int(cornering)
        keep = np.r_[
            np.arange(n2), *(np.arange(m) + n2 * (1 + b) for b in range(3)), np.arange(4 * n2, 4 * n2 + n_tail)
        ]
        (WT, XT), *rest = [(np.ascontiguousarray(W[keep].T), X) for W, X in stacked]
        vy_low, vy_high = aug.nts.bounds.lateral_speed_bounds
        one_set = cls(
            gains=gains,
            WT=WT,
            XT=XT,
            m=m,
            E=gains.E,
            E_is_zero=not np.any(gains.E),
            K_rows=K_rows,
            n=n,
            n_rules=r,
            premise_low=aug.nts.premise_low,
            premise_high=aug.nts.premise_high,
            vy_low=vy_low,
            vy_high=vy_high,
            measured_low=np.array([[1.0 / aug.nts.premise_high[0]], [aug.nts.premise_low[1]]]),
            measured_high=np.array([[1.0 / aug.nts.premise_low[0]], [aug.nts.premise_high[1]]]),
            rolling=rolling,
            cornering=cornering,
            two_C_f=2.0 * gains.params.front_cornering_stiffness_npr,
            l_f=gains.params.front_axle_distance_m,
            b_delta=gains.params.steer_fault_gain,
            steer_max=aug.nts.bounds.steer_max_rad,
            front_force_max=front_force_bound_n(aug.nts) if cornering else np.inf,
            steer_lag=gains.params.steer_lag_factor,
            steer_lag_mean=gains.params.steer_lag_mean_factor,
            load_transfer=gains.params.cg_height_m != 0.0,
        )
        if not rest or rule is None:
            return one_set
        return _with_quiet_set(one_set, rest[0], rule, gains.params.sample_period_s)

    @property
    def switched(self) -> bool:
        """Two gain sets (a switched design)."""
        return self.WT_quiet is not None


def _innovation_scale(gains: ObserverGains) -> FloatArray:
    """(2,) the switching statistic's weights of the innovation: sqrt((1 - lambda) / 2) over the sensor sigmas."""
    rule, noise = gains.options.switching, gains.options.noise
    if rule is None:
        raise BadParameters("the innovation statistic needs a switched design (options.switching)")
    weight = np.sqrt(0.5 * (1.0 - rule.forgetting))
    return weight / np.array([noise.vx_sigma_mps, noise.r_sigma_radps])


def _blended_rows(W: list[FloatArray], n: int) -> int:
    """m, such that x' = x[:m] holds the rows of x = [y; z] that some set's premise-dependent blocks (Q_V, Q_r,
    Q_Vr) of its feature weights W (n_features, n) use."""
    n2 = n + 2
    used = np.zeros(n2, dtype=bool)
    for W_set in W:
        used |= np.any(W_set[n2 : 4 * n2].reshape(3, n2, n) != 0.0, axis=(0, 2))
    return int(np.flatnonzero(used)[-1]) + 1 if used.any() else 0


def _stacked_gains(
    gains: ObserverGains, K_rows: np.ndarray, innovation_scale: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """(W, X^T) of :class:`RuntimeGains` for one gain set, before x' is cut out of W's blocks: W maps
    [x; V_x x; r x; V_x r x; g monomials; u; phi] to z_{k+1} (rows) and X^T maps x = [y; z] to the
    reported rows ``K_rows`` and, for a switched design, the weighted innovation
    ``innovation_scale`` (y - C x_hat). X^T C-contiguous."""
    aug = gains.model
    n = gains.N.shape[1]
    MT1 = gains.M @ aug.T1
    # Q_i = [L_i, N_i]^T, (n + 2, n): the rule's map of x = [y; z]
    Q = np.concatenate([gains.L, gains.N], axis=2).transpose(0, 2, 1)
    dQ_a, dQ_b, dQ_ab = Q[1] - Q[3], Q[2] - Q[3], Q[0] - Q[1] - Q[2] + Q[3]
    # a = (V_hi - V_x) / (V_hi - V_lo) = a_0 + a_1 V_x, b = (r_hi - r) / (r_hi - r_lo) = b_0 + b_1 r
    lo, hi = aug.nts.premise_low, aug.nts.premise_high
    a_1, b_1 = -1.0 / (hi[0] - lo[0]), -1.0 / (hi[1] - lo[1])
    a_0, b_0 = -hi[0] * a_1, -hi[1] * b_1
    bilinear = [
        Q[3] + a_0 * dQ_a + b_0 * dQ_b + a_0 * b_0 * dQ_ab,
        a_1 * dQ_a + a_1 * b_0 * dQ_ab,
        b_1 * dQ_b + a_0 * b_1 * dQ_ab,
        a_1 * b_1 * dQ_ab,
    ]
    extra = []
    if gains.params.rolling_resistance_n != 0.0:
        extra.append((MT1 @ g_constant(gains))[None, :])
    if aug.nts.has_cornering_drag:
        extra.append((gains.M @ aug.G_c_bar).T)
    W = np.vstack([*bilinear, (MT1 @ g_feature_matrix(gains)).T, (MT1 @ aug.nts.B).T, (gains.M @ aug.G_bar).T, *extra])
    # maps of x = [y; z], one row each
    rows: list[FloatArray] = [np.zeros((0, n + 2))]
    K = gains.output_gain
    if K_rows.size:
        # reported rows: (I - K C)(z - E y) + K y = F_y y + F_z z
        F_z = (np.eye(n) - K @ aug.C_bar)[K_rows]
        rows.append(np.concatenate([K[K_rows] - F_z @ gains.E, F_z], axis=1))
    if innovation_scale is not None:
        # nu = y - C (z - E y) = (I + C E) y - C z, weighted
        C = aug.C_bar
        nu = np.concatenate([np.eye(C.shape[0]) + C @ gains.E, -C], axis=1)
        rows.append(innovation_scale[:, None] * nu)
    return W, np.ascontiguousarray(np.vstack(rows))


@dataclass(slots=True)
class StepResult(AugmentedEstimate):
    """Output of one observer step for a batch.

    x_hat : (nv, n) reported estimate of x_bar_k: [v_x, v_y, r, T_f, delta_f, ...] (with the output gain)
    in_domain : (nv,) the measured premise lay in the design box
    vy_in_bounds : (nv,) the estimated v_y lay in [v_y,min, v_y,max] (and, with the cornering drag, the
        estimated applied steering angle delta_d + b_delta delta_f_hat in [-delta_max, delta_max])
    fast : (nv,) for a switched design, the fast gain set produced this step
    """

    x_hat: FloatArray
    in_domain: np.ndarray
    vy_in_bounds: np.ndarray
    #: (nv,) the fast set ran (switched designs; None for one gain set); a shared read-only array when every
    #: vehicle of the batch ran the same set
    fast: np.ndarray | None = None
    #: (nv, 2) the innovation y_k - C x_hat_k divided by the sensor sigmas and weighted by sqrt((1 - lambda) / 2),
    #: so that its squared norm is the switching statistic's increment (switched designs; None otherwise)
    innovation: FloatArray | None = None

    @property
    def certified(self) -> np.ndarray:
        """(nv,) the certificate covers this step: the premise in the box, v_y_hat and the applied angle in their
        bounds (outside, the error bound of the design does not hold and the fault alarms do not judge)."""
        return self.in_domain & self.vy_in_bounds


def initial_observer_state(
    rt: RuntimeGains, y: ArrayLike, x_hat0: ArrayLike | None = None, u0: ArrayLike | None = None
) -> FloatArray:
    """z_0 such that x_hat_0 = z_0 - E y_0 equals ``x_hat0``.

    Parameters
    ----------
    rt : RuntimeGains
        The gains in runtime form.
    y : (nv, 2) array_like
        First measurement [v_x [m/s], r [rad/s]].
    x_hat0 : (nv, n) or (nv, 3) array_like, optional
        The initial estimate; a 3-vector sets the vehicle state with zero faults. None: [v_x, 0, r] from y.
    u0 : (nv, 2) array_like, optional
        First demand [T_d [N m], delta_d [rad]]: with a steering actuator lag, its model starts at rest on the
        demanded angle (at 0 without u0).

    Returns
    -------
    (nv, state_size) ndarray
        z_0.
    """
    y = np.atleast_2d(np.asarray(y, dtype=float))
    nv = y.shape[0]
    x0 = np.zeros((nv, rt.n))
    if x_hat0 is None:
        x0[:, 0] = y[:, 0]
        x0[:, 2] = y[:, 1]
    else:
        given = np.atleast_2d(np.asarray(x_hat0, dtype=float))
        x0[:, : given.shape[1]] = given
    z0 = x0 + y @ rt.E.T
    if rt.steer_lag == 0.0:
        return z0
    if u0 is None:
        return np.column_stack([z0, np.zeros(nv)])
    steer0 = model_demand(y, np.atleast_2d(np.asarray(u0, dtype=float)), rt.gains.params)[:, 1]
    return np.column_stack([z0, steer0])


def observer_step(
    rt: RuntimeGains,
    z: FloatArray,
    y: ArrayLike,
    u: ArrayLike,
    fast: np.ndarray | None = None,
    mixed: bool | None = None,
) -> tuple[FloatArray, StepResult]:
    """One step of Algorithm 1 for a batch.

    Internally the batch is laid out vehicles-last (structure of arrays), so every elementwise loop runs over the
    fleet; the returned z_{k+1} is the transpose of a contiguous (n, nv) array, which makes the next call's
    transposes free.

    Parameters
    ----------
    rt : RuntimeGains
        The gains in runtime form.
    z : (nv, state_size) ndarray
        Observer state z_k.
    y : (nv, 2) array_like
        Measured [v_x [m/s], r [rad/s]]; finite.
    u : (nv, 2) array_like
        Demanded [T_d [N m], delta_d [rad]]; finite.
    fast : (nv,) bool ndarray, optional
        For a switched design, which vehicles use the fast set (None: all of them). The features are shared, so a
        mixed batch costs one GEMM with both sets stacked.
    mixed : bool, optional
        Whether ``fast`` has both True and False, when the caller knows already.

    Returns
    -------
    z_next : (nv, state_size) ndarray
        z_{k+1}.
    result : StepResult
        The estimate at k and its flags.

    Raises
    ------
    ShapeError
        y, u or z does not have the batch's shape (the message names it).
    """
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    nv = y.shape[0]
    if y.shape != (nv, 2) or u.shape != (nv, 2) or z.shape != (nv, rt.state_size):
        _check_batch(rt, z, y, u)
    if rt.load_transfer:  # the model's input: the demand with the load transfer's steering angle
        u = model_demand(y, u, rt.gains.params)
    Phi, x, in_domain, vy_in_bounds = _features(rt, z, y, u)
    z_rows, x_rows = _gain_products(rt, Phi, x, fast, mixed)
    n, k = rt.n, rt.K_rows.size
    lagged = rt.steer_lag != 0.0
    z_next = (_with_actuator(rt, z_rows, z, u) if lagged else z_rows).T
    # the reported estimate: x_hat_k + K (y_k - C_bar x_hat_k), every row out of the small GEMM, when
    # there is an output gain; else x_hat_k = z_k - E y_k (line 8)
    z_obs = z[:, :n] if lagged else z
    x_hat = x_rows[:k].T if k else (z_obs if rt.E_is_zero else z_obs - y @ rt.E.T)
    innovation = x_rows[k:].T if rt.WT_quiet is not None else None
    mask = None if rt.WT_quiet is None else (_constant_mask(nv, True) if fast is None else fast)
    return z_next, StepResult(
        x_hat=x_hat, in_domain=in_domain, vy_in_bounds=vy_in_bounds, fast=mask, innovation=innovation
    )


def _features(
    rt: RuntimeGains, z: FloatArray, y: FloatArray, u: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray, np.ndarray]:
    """Lines 8-9 of Algorithm 1 up to the gains: the feature matrix Phi, shape (n_features, nv), vehicles last.

    Returns (Phi, x, in_domain, vy_in_bounds): x = Phi[:n + 2] is the constant block [y; z] (without the
    actuator's column), in_domain and vy_in_bounds are those of :class:`StepResult`.
    """
    nv = y.shape[0]
    n, n2, m = rt.n, rt.n + 2, rt.m
    tail = n2 + 3 * m  # first row after the rule blend: [v_x^2, r/v_x, v_x r, u, phi, (1), (phi_c)]
    Phi = np.empty((rt.n_features, nv))
    x = Phi[:n2]  # the constant block [y; z]: filled first, every loop at unit stride
    x[:2] = y.T
    lagged = rt.steer_lag != 0.0
    x[2:] = z[:, :n].T if lagged else z.T
    yT = x[:2]
    Phi[tail + 3 : tail + 5] = u.T
    if lagged:  # the model's steering input: the actuator's angle over the sample, from the last column of z
        np.subtract(u[:, 1], z[:, n], out=Phi[tail + 4])
        Phi[tail + 4] *= rt.steer_lag_mean
        Phi[tail + 4] += z[:, n]
    # line 8: x_hat_k = z_k - E y_k
    vy_hat = x[2 + VY_INDEX] if rt.E_is_zero else z[:, VY_INDEX] - y @ rt.E[VY_INDEX]
    # premise xi = [1/v_x, r], clipped to the design box, flagged when the clip moved it. Ufuncs, not
    # np.clip, throughout the step: np.clip and the array methods (max, any) go through Python
    # wrappers that cost microseconds each when the caches are cold, as next to an EKF's step
    measured = np.empty((3, nv))  # [v_x, r, V_x = 1 / v_x], clipped
    clipped = np.minimum(np.maximum(yT, rt.measured_low, out=measured[:2]), rt.measured_high, out=measured[:2])
    same = clipped == yT
    in_domain = same[0] & same[1]
    v_x, r, V_x = measured[0], measured[1], measured[2]
    np.divide(1.0, v_x, out=V_x)
    V_x_r = np.multiply(V_x, r, out=Phi[tail + 1])  # also the monomial r / v_x of g
    # line 9 as W^T Phi: [x, V_x x', r x', V_x r x'] (the rule blend), the monomials of g, u, phi(sat(v_y_hat))
    for i, multiplier in enumerate((V_x, r, V_x_r)):  # three 2-d products cost less than one 3-d broadcast
        np.multiply(multiplier, x[:m], out=Phi[n2 + i * m : n2 + (i + 1) * m])
    np.multiply(v_x, clipped, out=Phi[tail : tail + 3 : 2])  # v_x^2 and v_x r
    vy_sat = np.minimum(np.maximum(vy_hat, rt.vy_low, out=Phi[tail + 5]), rt.vy_high, out=Phi[tail + 5])
    vy_in_bounds = vy_sat == vy_hat
    if rt.rolling:
        Phi[tail + 6] = 1.0
    if rt.cornering:
        vy_in_bounds &= _cornering_drag(rt, Phi[-1], x, z, y, Phi[tail + 4], vy_sat, r, V_x)
    np.multiply(vy_sat, vy_sat, out=vy_sat)
    return Phi, x, in_domain, vy_in_bounds


def _gain_products(
    rt: RuntimeGains, Phi: FloatArray, x: FloatArray, fast: np.ndarray | None, mixed: bool | None
) -> tuple[FloatArray, FloatArray]:
    """Line 9's z_{k+1} rows W^T Phi, shape (n, nv), and the reported rows X^T x (the output gain's estimate,
    then the weighted innovation), from the set each vehicle runs: one GEMM each for a batch on one set, or
    for a mixed batch both sets stacked, the fast vehicles' columns copied over the quiet ones (of the reported
    rows, only ``rt.fast_rows``, the rows where the sets differ)."""
    n, nv = rt.n, Phi.shape[1]
    WT_quiet, WT_pair, XT_quiet, XT_pair = rt.WT_quiet, rt.WT_pair, rt.XT_quiet, rt.XT_pair
    if mixed is None and fast is not None:
        mixed = 0 < np.count_nonzero(fast) < nv
    all_fast = fast is None or (not mixed and (nv == 0 or bool(fast[0])))
    if WT_quiet is None or WT_pair is None or XT_quiet is None or XT_pair is None or all_fast:
        return rt.WT @ Phi, rt.XT @ x
    if not mixed:
        return WT_quiet @ Phi, XT_quiet @ x
    both = WT_pair @ Phi
    z_rows = both[n:]
    np.copyto(z_rows, both[:n], where=fast)
    x_both = XT_pair @ x  # [quiet set's reported rows; innovation; fast set's reported rows fast_rows]
    x_rows = x_both[: XT_quiet.shape[0]]
    np.copyto(x_rows[rt.fast_rows], x_both[XT_quiet.shape[0] :], where=fast)
    return z_rows, x_rows


def _with_actuator(rt: RuntimeGains, z_rows: FloatArray, z: FloatArray, u: FloatArray) -> FloatArray:
    """z_{k+1}'s rows, shape (n + 1, nv), with the steering actuator's model appended as the last row."""
    n, nv = rt.n, z_rows.shape[1]
    # the actuator model: delta_{k+1} = a delta_k + (1 - a) delta_d,k
    full = np.empty((n + 1, nv))
    full[:n] = z_rows
    np.multiply(z[:, n], rt.steer_lag, out=full[n])
    full[n] += (1.0 - rt.steer_lag) * u[:, 1]
    return full


def _check_batch(rt: RuntimeGains, z: FloatArray, y: FloatArray, u: FloatArray) -> None:
    """Raise :class:`~synth.errors.ShapeError` naming the first of y, u, z whose shape does not fit the batch."""
    nv = y.shape[0] if y.ndim else 0
    check_shape(y, (nv, 2), "y")
    check_shape(u, (nv, 2), "u")
    check_shape(z, (nv, rt.state_size), "z")


def _cornering_drag(
    rt: RuntimeGains,
    out: FloatArray,
    x: FloatArray,
    z: FloatArray,
    y: FloatArray,
    steer_demand: FloatArray,
    vy_sat: FloatArray,
    r: FloatArray,
    V_x: FloatArray,
) -> np.ndarray:
    """phi_c = F_yf sin(delta) at the estimates, written to ``out`` (nv,); returns where delta was in bounds.

    delta = sat(delta_d + b_delta delta_f_hat) to [-delta_max, delta_max], v_y = sat(v_y_hat), and
    F_yf = sat(2 C_f (delta - (v_y + l_f r) V_x)) to [-F_max, F_max], with the clipped premise (V_x, r):
    with the true values in their bounds, each saturation is 1-Lipschitz and moves towards them, so the
    DMVT bounds of synth.augmented hold as they do for phi = v_y^2.
    """
    row = STEER_FAULT_INDEX
    delta_f_hat = x[2 + row] if rt.E_is_zero else z[:, row] - y @ rt.E[row]
    delta = steer_demand + rt.b_delta * delta_f_hat
    in_bounds = np.abs(delta) <= rt.steer_max
    np.minimum(np.maximum(delta, -rt.steer_max, out=delta), rt.steer_max, out=delta)
    # F_yf = 2 C_f (delta - (v_y + l_f r) V_x)
    F_yf = delta - (vy_sat + rt.l_f * r) * V_x
    F_yf *= rt.two_C_f
    np.minimum(np.maximum(F_yf, -rt.front_force_max, out=F_yf), rt.front_force_max, out=F_yf)
    # phi_c = F_yf sin(delta)
    np.multiply(F_yf, np.sin(delta), out=out)
    return in_bounds


_MASKS = {False: np.zeros(0, dtype=bool), True: np.ones(0, dtype=bool)}


def _constant_mask(nv: int, value: bool) -> np.ndarray:
    """A read-only (nv,) mask of ``value``: a view of one shared array, grown when a larger batch comes."""
    shared = _MASKS[value]
    if shared.shape[0] < nv:
        shared = np.full(max(nv, 2 * shared.shape[0]), value)
        shared.flags.writeable = False
        _MASKS[value] = shared
    return shared[:nv]


def switched_step(
    rt: RuntimeGains, z: FloatArray, stat: FloatArray, left: np.ndarray, y: ArrayLike, u: ArrayLike
) -> tuple[FloatArray, FloatArray, np.ndarray, StepResult]:
    """One step with the switching rule.

    For gains with one set this is :func:`observer_step`, with ``stat`` and ``left`` passed through. Otherwise::

        fast set at k if left > 0;   nu_k = (y_k - C x_hat_k) / sigma   (out of the small GEMM on [y; z])
        s_k = lambda s_{k-1} + (1 - lambda) |nu_k|^2 / 2
        left <- max(left - 1, 0), then max(left, hold) where s_k > threshold

    so a statistic above the threshold at k puts the fast set on from k + 1 for ``hold`` samples.

    Parameters
    ----------
    rt, z, y, u
        As for :func:`observer_step`.
    stat : (nv,) ndarray
        The statistic s_{k-1}.
    left : (nv,) int ndarray
        Samples the fast set still has to run, counting this one (``rt.start_samples`` at a (re)start; 0 and a
        statistic of 0 are a settled vehicle).

    Returns
    -------
    z_next : (nv, state_size) ndarray
        z_{k+1}.
    stat : (nv,) ndarray
        s_k.
    left : (nv,) int ndarray
        Fast samples left after this one.
    result : StepResult
        The estimate at k, with the set each vehicle ran.

    Raises
    ------
    ShapeError
        y, u or z does not have the batch's shape.
    """
    if rt.WT_quiet is None:
        z_next, result = observer_step(rt, z, y, u)
        return z_next, stat, left, result
    # a settled fleet has no vehicle on the fast set, a starting one all: then no mask arithmetic
    nv = left.shape[0]
    any_fast = nv > 0 and np.maximum.reduce(left) > 0
    all_fast = any_fast and np.minimum.reduce(left) > 0
    fast = left > 0 if any_fast and not all_fast else _constant_mask(nv, all_fast)
    z_next, result = observer_step(rt, z, y, u, fast, mixed=any_fast and not all_fast)
    nu = result.innovation
    assert nu is not None  # a switched runtime always reports it
    energy = np.square(nu.T)  # (2, nv): the GEMM's rows, contiguous, already weighted by sqrt((1 - lambda) / 2)
    stat = stat * rt.switch_forgetting
    stat += energy[0]
    stat += energy[1]
    if any_fast:  # one sample of the fast set used, never below 0
        left = left - 1 if all_fast else left - fast
    if stat.size and np.maximum.reduce(stat) > rt.switch_threshold:
        exceeded = stat > rt.switch_threshold
        left = left.copy() if not any_fast else left
        left[exceeded] = np.maximum(left[exceeded], rt.hold_samples)
    return z_next, stat, left, result


class FuzzyObserver:
    """A fixed batch of observers sharing one design (one gain set, or a switched pair), with its state."""

    def __init__(
        self, gains: ObserverGains, y0: ArrayLike, x_hat0: ArrayLike | None = None, u0: ArrayLike | None = None
    ) -> None:
        self.runtime = RuntimeGains.from_gains(gains)
        self.z = initial_observer_state(self.runtime, y0, x_hat0, u0)
        # the switching rule's per-vehicle state; empty for one gain set
        rows = self.n_vehicles if self.runtime.switched else 0
        self.stat: FloatArray = np.zeros(rows)
        self.left: np.ndarray = np.full(rows, self.runtime.start_samples, dtype=np.int64)

    @property
    def n_vehicles(self) -> int:
        return int(self.z.shape[0])

    def step(self, y: ArrayLike, u: ArrayLike) -> StepResult:
        """Consume y_k, u_k; return the estimate at k and advance to k + 1.

        Parameters
        ----------
        y : (nv, 2) array_like
            Measured [v_x [m/s], r [rad/s]].
        u : (nv, 2) array_like
            Demanded [T_d [N m], delta_d [rad]].

        Returns
        -------
        StepResult
            The estimate at k.
        """
        self.z, self.stat, self.left, result = switched_step(
            self.runtime, self.z, self.stat, self.left, np.atleast_2d(y), np.atleast_2d(u)
        )
        return result


def _with_quiet_set(
    one_set: RuntimeGains, quiet: tuple[FloatArray, FloatArray], rule: SwitchingRule, period: float
) -> RuntimeGains:
    """``one_set`` (the fast set's runtime gains) with the quiet set's stacked weights ``quiet`` = (WT, XT) and the
    switching rule of a switched design (docs/switched-gains.md); a mixed batch picks per vehicle only the output
    rows where the two sets' output gains differ."""
    WT, XT, k = one_set.WT, one_set.XT, one_set.K_rows.size
    WT_quiet, XT_quiet = quiet
    differ = np.flatnonzero(np.any(XT[:k] != XT_quiet[:k], axis=1))
    fast_rows = slice(int(differ[0]), int(differ[-1]) + 1) if differ.size else slice(0, 0)
    return replace(
        one_set,
        WT_quiet=WT_quiet,
        WT_pair=np.vstack([WT, WT_quiet]),
        XT_quiet=XT_quiet,
        XT_pair=np.vstack([XT_quiet, XT[fast_rows]]),
        fast_rows=fast_rows,
        switch_threshold=rule.threshold,
        switch_forgetting=rule.forgetting,
        hold_samples=round(rule.hold_s / period),
        start_samples=round(rule.start_s / period),
    )

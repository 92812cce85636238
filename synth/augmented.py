"""The augmented fault model (eqs. 17-18), with a configurable fault-model order.

The fault f_k = [T_f, delta_f] is modelled per channel as a q-fold integrator,
char. polynomial (z - 1)^q. q = 3 is the paper's triple integrator (eq. 17);
q = 1 (constant / random-walk faults) and q = 2 (ramps) are offered because
they trade tracking bandwidth against noise sensitivity (NOTES.md, finding 5).

Augmented state x_bar = [x; f_k; f_{k+1}; ...; f_{k+q-1}] (shift coordinates,
as printed), dimension n = 3 + 2 q:

    x_bar_{k+1} = A_bar(h) x_bar_k + T1 (B u_k + g(xi_k)) + G_bar phi(x_bar_k) + D_bar d_k
                  [+ G_c_bar phi_c(x_bar_k, u_k) with the cornering drag]
    y_k = C_bar x_bar_k

The unmeasured nonlinearities enter the error dynamics through the DMVT
(Lemma 1, eq. 26): phi(x) - phi(x_hat) = sum_k rho_k c_k^T e with each rho_k a
partial derivative bounded over the operating box. :meth:`AugmentedModel.dmvt_terms`
lists them, the one place they are defined: d(v_y^2)/dv_y of the paper, and
with the cornering drag phi_c = F_yf sin(delta) its derivatives in v_y and in
the steering fault (through delta = delta_d + b_delta delta_f).

:func:`difference_coordinates` gives the change of basis to
[x; f; Delta f; Delta^2 f], in which the fault chain is a Jordan block: the same
system, better conditioned for the solver (NOTES.md, finding 2).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np

from synth.errors import BadParameters
from synth.fuzzy import NTSModel
from synth.model import FloatArray

N_STATES = 3
N_FAULTS = 2
N_OUTPUTS = 2
#: Index of v_y in the plant state and in the augmented state.
VY_INDEX = 1


class AugmentedEstimate:
    """What a batch's estimate of the augmented state reads as: ``x_hat`` of shape (nv, n), rows
    [v_x, v_y, r, T_f, delta_f, ...]. The observer's and the EKF's results both carry it."""

    __slots__ = ()
    x_hat: FloatArray

    @property
    def state(self) -> FloatArray:
        """(nv, 3) estimated [v_x [m/s], v_y [m/s], r [rad/s]]."""
        return self.x_hat[:, :N_STATES]

    @property
    def faults(self) -> FloatArray:
        """(nv, 2) estimated [T_f [N m], delta_f [rad]]."""
        return self.x_hat[:, N_STATES : N_STATES + N_FAULTS]


def fault_chain_matrix(order: int) -> FloatArray:
    """The block companion matrix of (z - 1)^order in shift coordinates.

    Order 3 gives eq. (17): the bottom block row is [I, -3I, 3I].

    Parameters
    ----------
    order : int
        q, how many samples of each fault channel the chain holds (1, 2 or 3).

    Returns
    -------
    (2q, 2q) ndarray
        The fault chain's transition matrix.

    Raises
    ------
    BadParameters
        ``order`` is not 1, 2 or 3.
    """
    _check_order(order)
    q = order
    I2 = np.eye(N_FAULTS)
    chain = np.zeros((N_FAULTS * q, N_FAULTS * q))
    for block in range(q - 1):
        chain[N_FAULTS * block : N_FAULTS * (block + 1), N_FAULTS * (block + 1) : N_FAULTS * (block + 2)] = I2
    # f_{k+q} = -sum_{m=0}^{q-1} binom(q, m) (-1)^(q-m) f_{k+m}
    for m in range(q):
        coeff = -comb(q, m) * (-1) ** (q - m)
        chain[N_FAULTS * (q - 1) :, N_FAULTS * m : N_FAULTS * (m + 1)] = coeff * I2
    return chain


def _check_order(order: int) -> None:
    if order not in (1, 2, 3):
        raise BadParameters(f"fault_order must be 1, 2 or 3, got {order!r}")


@dataclass(frozen=True)
class DMVTTerm:
    """One scalar of the DMVT (eq. 26) in the error dynamics: rho G c^T e, with rho in [low, high].

    name : what rho is, e.g. "d(v_y^2)/dv_y"
    G : (n, 1) where the nonlinearity enters the augmented state (G_bar or G_c_bar)
    row : (1, n) the error component that rho multiplies, c^T (a unit row)
    low, high : bounds of rho over the operating box (and the fault bounds), low <= high
    """

    name: str
    G: FloatArray
    row: FloatArray
    low: float
    high: float

    @property
    def centre(self) -> float:
        return 0.5 * (self.low + self.high)

    @property
    def radius(self) -> float:
        return 0.5 * (self.high - self.low)

    def matrix(self, M: FloatArray | None = None) -> FloatArray:
        """(M) G c^T, (n, n): the error term per unit rho; M = I unless given (the observer's M of eq. 20)."""
        G = self.G if M is None else M @ self.G
        return G @ self.row

    def transformed(self, T: FloatArray, T_inv: FloatArray) -> DMVTTerm:
        """The same term in coordinates x' = T x_bar: G' = T G, c'^T = c^T T^-1."""
        return DMVTTerm(self.name, T @ self.G, self.row @ T_inv, self.low, self.high)


def front_force_bound_n(nts: NTSModel) -> float:
    """F_max, the bound of |F_yf| [N] the cornering drag's observer saturates to and its DMVT bounds use.

    The bounds' ``front_lateral_force_max_n`` when given, never more than what the operating box allows:
    2 C_f (delta_max + w_max), w_max = (max |v_y| + l_f max |r|) / v_x,min.

    Parameters
    ----------
    nts : NTSModel
        The model: its vehicle and operating box.

    Returns
    -------
    float
        F_max [N].
    """
    bounds, k = nts.bounds, nts.params.symbols()
    vy_abs = max(abs(bounds.vy_min_mps), abs(bounds.vy_max_mps))
    r_abs = max(abs(bounds.r_min_radps), abs(bounds.r_max_radps))
    w_max = (vy_abs + k["l_f"] * r_abs) / bounds.vx_min_mps
    box = 2.0 * k["C_f"] * (bounds.steer_max_rad + w_max)
    given = bounds.front_lateral_force_max_n
    return box if given is None else min(box, given)


def dmvt_vertices(terms: tuple[DMVTTerm, ...]) -> list[tuple[float, ...]]:
    """Every vertex of the box of (rho_1, ..., rho_K).

    Parameters
    ----------
    terms : tuple of DMVTTerm
        The K DMVT terms, whose bounds span the box.

    Returns
    -------
    list of tuple of float
        The 2^K vertices, the lower bounds first.
    """
    return list(itertools.product(*((t.low, t.high) for t in terms)))


@dataclass(frozen=True)
class AugmentedModel:
    """The augmented N-TS fault model of eq. (18).

    A_bar : (4, n, n)  [[A_i, F, 0], [0, fault chain]]
    T1    : (n, 3)     [I; 0]
    B_bar : (n, 2)     T1 B
    G_bar : (n, 1)     T1 G
    G_c_bar : (n, 1)   T1 G_c (zero without the cornering drag)
    D_bar : (n, 1)     T1 D
    C_bar : (2, n)     [C, 0]
    n = 3 + 2 * fault_order; the current fault f_k sits at indices 3 and 4.
    """

    nts: NTSModel
    fault_order: int
    A_bar: FloatArray
    T1: FloatArray
    B_bar: FloatArray
    G_bar: FloatArray
    G_c_bar: FloatArray
    D_bar: FloatArray
    C_bar: FloatArray

    @classmethod
    def build(cls, nts: NTSModel, fault_order: int = 3) -> AugmentedModel:
        """The augmented model of eqs. (17)-(18) for ``nts`` and a fault chain of ``fault_order``.

        Parameters
        ----------
        nts : NTSModel
            The vehicle's N-TS model.
        fault_order : int, default 3
            The fault model's order q: 1, 2 or 3 (3 is the paper's).

        Returns
        -------
        AugmentedModel
            A_bar_i, T1, B_bar, G_bar, G_c_bar, D_bar and C_bar, n = 3 + 2 q.

        Raises
        ------
        BadParameters
            A fault order other than 1, 2 or 3.
        """
        _check_order(fault_order)
        n = N_STATES + N_FAULTS * fault_order
        A_bar = np.zeros((nts.n_rules, n, n))
        A_bar[:, :N_STATES, :N_STATES] = nts.A
        A_bar[:, :N_STATES, N_STATES : N_STATES + N_FAULTS] = nts.F
        A_bar[:, N_STATES:, N_STATES:] = fault_chain_matrix(fault_order)
        T1 = np.zeros((n, N_STATES))
        T1[:N_STATES, :N_STATES] = np.eye(N_STATES)
        C_bar = np.zeros((N_OUTPUTS, n))
        C_bar[:, :N_STATES] = nts.C
        return cls(
            nts=nts,
            fault_order=fault_order,
            A_bar=A_bar,
            T1=T1,
            B_bar=T1 @ nts.B,
            G_bar=T1 @ nts.G,
            G_c_bar=T1 @ nts.G_c,
            D_bar=T1 @ nts.D,
            C_bar=C_bar,
        )

    @property
    def n(self) -> int:
        """Dimension of the augmented state."""
        return int(self.A_bar.shape[1])

    @property
    def fault_slice(self) -> slice:
        """Where f_k sits in the augmented state."""
        return slice(N_STATES, N_STATES + N_FAULTS)

    def A_bar_at(self, h: FloatArray) -> FloatArray:
        """A_bar(h) = sum_i h_i A_bar_i for memberships h of shape (..., 4); returns (..., n, n)."""
        return np.einsum("...i,ijk->...jk", h, self.A_bar)

    def unit_row(self, index: int) -> FloatArray:
        """e_index^T, (1, n)."""
        row = np.zeros((1, self.n))
        row[0, index] = 1.0
        return row

    @cached_property
    def dmvt_terms(self) -> tuple[DMVTTerm, ...]:
        """The scalars of the DMVT (eq. 26) and their bounds over the operating box.

        phi = v_y^2 (eq. 15): rho = 2 v_y in [2 v_y,min, 2 v_y,max], entering through G_bar.
        With the cornering drag, phi_c = F_yf sin(delta), F_yf = 2 C_f (delta - w), w = (v_y + l_f r) V_x.
        The observer evaluates it as sat(F_yf_hat) sin(sat(delta_hat)), both saturated to their bounds
        (synth.observer), so by the mean value theorem on (F, delta) -> F sin(delta) over the box
        |F| <= F_max, |delta| <= delta_max, with the saturations' factors kappa in [0, 1]:

            phi_c - phi_c_hat = -2 C_f V_x kappa_F sin(delta_c) e_vy
                                + (2 C_f kappa_F sin(delta_c) + F_c cos(delta_c)) kappa_delta b_delta e_deltaf

            |rho_vy| <= 2 C_f V_max sin(delta_max),   |rho_deltaf| <= b_delta (2 C_f sin(delta_max) + F_max)

        F_max is the bound's ``front_lateral_force_max_n`` when given (a physical bound, the grip), and
        never more than what the box allows, 2 C_f (delta_max + w_max) with w_max = (max |v_y| + l_f max |r|)
        V_max. Both intervals are symmetric about zero, as the mirror symmetry needs (synth.symmetry).
        """
        nts = self.nts
        bounds, k = nts.bounds, nts.params.symbols()
        vy_lo, vy_hi = bounds.lateral_speed_bounds
        terms = [DMVTTerm("d(v_y^2)/dv_y", self.G_bar, self.unit_row(VY_INDEX), 2.0 * vy_lo, 2.0 * vy_hi)]
        if nts.has_cornering_drag:
            V_max = 1.0 / bounds.vx_min_mps
            delta_max = bounds.steer_max_rad
            d_vy = 2.0 * k["C_f"] * V_max * np.sin(delta_max)
            d_delta = k["b_delta"] * (2.0 * k["C_f"] * np.sin(delta_max) + front_force_bound_n(nts))
            delta_f = self.unit_row(N_STATES + 1)
            terms.append(DMVTTerm("dphi_c/dv_y", self.G_c_bar, self.unit_row(VY_INDEX), -d_vy, d_vy))
            terms.append(DMVTTerm("dphi_c/ddelta_f", self.G_c_bar, delta_f, -d_delta, d_delta))
        return tuple(terms)


def difference_coordinates(fault_order: int) -> FloatArray:
    """The change to difference coordinates of the fault chain.

    Delta^m f = sum_j binom(m, j) (-1)^(m-j) f_{k+j}: finite differences of the shift-coordinate fault chain.

    Parameters
    ----------
    fault_order : int
        The fault model's order q: 1, 2 or 3.

    Returns
    -------
    (n, n) ndarray
        T with x_diff = T x_bar, x_diff = [x; f; Delta f; ...], n = 3 + 2 q.

    Raises
    ------
    BadParameters
        ``fault_order`` is not 1, 2 or 3.
    """
    _check_order(fault_order)
    n = N_STATES + N_FAULTS * fault_order
    T = np.eye(n)
    for m in range(fault_order):
        rows = slice(N_STATES + N_FAULTS * m, N_STATES + N_FAULTS * (m + 1))
        T[rows, N_STATES:] = 0.0
        for j in range(m + 1):
            cols = slice(N_STATES + N_FAULTS * j, N_STATES + N_FAULTS * (j + 1))
            T[rows, cols] = comb(m, j) * (-1) ** (m - j) * np.eye(N_FAULTS)
    return T

"""The augmented fault model (eqs. 17-18), with a configurable fault-model order.

The fault f_k = [T_f, delta_f] is modelled per channel as a q-fold integrator,
char. polynomial (z - 1)^q. q = 3 is the paper's triple integrator (eq. 17);
q = 1 (constant / random-walk faults) and q = 2 (ramps) are offered because
they trade tracking bandwidth against noise sensitivity (NOTES.md, finding 5).

Augmented state x_bar = [x; f_k; f_{k+1}; ...; f_{k+q-1}] (shift coordinates,
as printed), dimension n = 3 + 2 q:

    x_bar_{k+1} = A_bar(h) x_bar_k + T1 (B u_k + g(xi_k)) + G_bar phi(x_bar_k) + D_bar d_k
    y_k = C_bar x_bar_k

:func:`difference_coordinates` gives the change of basis to
[x; f; Delta f; Delta^2 f], in which the fault chain is a Jordan block: the same
system, better conditioned for the solver (NOTES.md, finding 2).
"""

from __future__ import annotations

from dataclasses import dataclass
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


def fault_chain_matrix(order: int) -> FloatArray:
    """The block companion matrix of (z - 1)^order in shift coordinates, (2q, 2q).

    order 3 gives eq. (17): the bottom block row is [I, -3I, 3I].
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
class AugmentedModel:
    """The augmented N-TS fault model of eq. (18).

    A_bar : (4, n, n)  [[A_i, F, 0], [0, fault chain]]
    T1    : (n, 3)     [I; 0]
    B_bar : (n, 2)     T1 B
    G_bar : (n, 1)     T1 G
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
    D_bar: FloatArray
    C_bar: FloatArray

    @classmethod
    def build(cls, nts: NTSModel, fault_order: int = 3) -> AugmentedModel:
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

    def rho_row(self, rho: float) -> FloatArray:
        """The DMVT row of eq. (26): Delta phi = rho_row e, with only d phi/d v_y = rho non-zero, (1, n)."""
        row = np.zeros((1, self.n))
        row[0, VY_INDEX] = rho
        return row

    def rho_vertices(self) -> tuple[float, float]:
        """The vertices of S_rho: d(v_y^2)/d v_y = 2 v_y over [v_y,min, v_y,max]."""
        lo, hi = self.nts.bounds.lateral_speed_bounds
        return 2.0 * lo, 2.0 * hi


def difference_coordinates(fault_order: int) -> FloatArray:
    """T with x_diff = T x_bar, x_diff = [x; f; Delta f; ...], shape (n, n).

    Delta^m f = sum_j binom(m, j) (-1)^(m-j) f_{k+j}: finite differences of the
    shift-coordinate fault chain.
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

"""Takagi-Sugeno representations of the Euler-discretised vehicle (eqs. 14-16).

:class:`NTSModel` is the paper's N-TS model (eq. 15): 4 rules whose premise
xi = [V_x, r] = [1/v_x, r] is measured, a nonlinear consequent g(xi) of
measured signals only, and the unmeasured nonlinearity G phi(x), phi = v_y^2.
Typos of the printed eq. (15) are corrected as in NOTES.md: g_1 divides by
I_e (the effective mass m_eff), s multiplies both terms of g_2, g_3 carries the
factor r, and the numerator of h_2 is (r - r_min).

The longitudinal terms a real vehicle adds (synth.model) keep the form: the
rolling resistance is a constant in g_1, and the cornering drag
F_yf sin(delta) is a second unmeasured nonlinearity G_c phi_c(x, delta), with
G_c = [-s/m_eff, 0, 0]^T and phi_c = F_yf(v_y, delta) sin(delta) [N]; it
depends on the unmeasured v_y and, through the applied delta = delta_d +
b_delta delta_f, on the steering fault. The observer evaluates it at the
estimates and the DMVT bounds the difference (synth.augmented).

:class:`ConventionalTSModel` is the 8-rule sector-nonlinearity model of
eq. (14), premise [v_x, 1/v_x, v_y], kept for comparison (Remark 2): its
premise contains the unmeasured v_y.

Both are built from the parameters and bounds, never typed by hand.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike

from synth.errors import BadParameters
from synth.model import C, FloatArray, continuous_matrices
from synth.params import OperatingBounds, VehicleParams

#: Index of each premise corner (V_x, r) in the rule ordering of eq. (16):
#: rule 1 (low, low), rule 2 (low, high), rule 3 (high, low), rule 4 (high, high).
RULE_CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))


class InputMatrices(TypedDict):
    """The input matrices of the Euler-discretised model (eq. 14): B (3, 2), D (3, 1), F (3, 2)."""

    B: FloatArray
    D: FloatArray
    F: FloatArray


def euler_input_matrices(params: VehicleParams) -> InputMatrices:
    """B = s B_v, D = s D_v, F = s F_v of eq. (14), shared by the N-TS and the conventional TS model.

    Parameters
    ----------
    params : VehicleParams
        Gives the sample period s [s] and, through :func:`synth.model.continuous_matrices`, B_v, D_v, F_v.

    Returns
    -------
    InputMatrices
        B : (3, 2) on the demands [T_d, delta_d]; D : (3, 1) on the wind force; F : (3, 2) on the faults.
    """
    cm = continuous_matrices(params)
    s = params.sample_period_s
    return {"B": s * cm.B_v, "D": s * cm.D_v, "F": s * cm.F_v}


def sector_weights(z: ArrayLike, low: float, high: float) -> tuple[FloatArray, FloatArray]:
    """The two sector-nonlinearity weights of a scalar premise.

    ``z`` is not clipped here: callers clip to the design domain first.

    Parameters
    ----------
    z : array_like
        The premise, any shape (...).
    low, high : float
        The premise's bounds.

    Returns
    -------
    w_low, w_high : (...) ndarray
        w_low = (high - z) / (high - low) and w_high = 1 - w_low.
    """
    z = np.asarray(z, dtype=float)
    w_low = (high - z) / (high - low)
    return w_low, 1.0 - w_low


@dataclass(frozen=True)
class DiscreteTSModel:
    """What the TS models of eqs. (14) and (15) share: the vehicle and its operating box, the vertex matrices
    A (r, 3, 3), one per rule, and the input matrices B, D, F of :func:`euler_input_matrices`."""

    params: VehicleParams
    bounds: OperatingBounds
    A: FloatArray
    B: FloatArray
    D: FloatArray
    F: FloatArray


@dataclass(frozen=True)
class NTSModel(DiscreteTSModel):
    """The N-TS fuzzy model of eq. (15) with the memberships of eq. (16).

    A : (4, 3, 3)  vertex matrices A_i = A(V_x, r) at the premise corners
    B : (3, 2)     s B_v
    D : (3, 1)     s D_v
    F : (3, 2)     s F_v
    G : (3, 1)     [0, -s C_y/M_v, 0]^T
    G_c : (3, 1)   [-s/m_eff, 0, 0]^T, where the cornering drag phi_c enters (zero without ``cornering_drag``)
    C : (2, 3)     measurement matrix
    premise_low, premise_high : (2,)  bounds of xi = [V_x [s/m], r [rad/s]]
    """

    G: FloatArray
    G_c: FloatArray
    C: FloatArray
    premise_low: FloatArray
    premise_high: FloatArray

    @classmethod
    def build(cls, params: VehicleParams, bounds: OperatingBounds) -> NTSModel:
        """Build the vertex matrices from the parameters and the premise box.

        Parameters
        ----------
        params : VehicleParams
            The vehicle.
        bounds : OperatingBounds
            The operating box; its 1/v_x and r bounds are the premise box.

        Returns
        -------
        NTSModel
            The model of eq. (15).
        """
        V_lo, V_hi = bounds.inverse_speed_bounds
        r_lo, r_hi = bounds.yaw_rate_bounds
        corners = [(V_lo, V_hi)[a] for a, _ in RULE_CORNERS], [(r_lo, r_hi)[b] for _, b in RULE_CORNERS]
        A = np.stack([_vertex_matrix(V, r, params) for V, r in zip(*corners, strict=True)])
        s = params.sample_period_s
        G = np.array([[0.0], [-s * params.lateral_drag_coeff / params.mass_kg], [0.0]])
        G_c = np.array([[-s / params.effective_mass_kg if params.cornering_drag else 0.0], [0.0], [0.0]])
        return cls(
            params=params,
            bounds=bounds,
            A=A,
            **euler_input_matrices(params),
            G=G,
            G_c=G_c,
            C=C.copy(),
            premise_low=np.array([V_lo, r_lo]),
            premise_high=np.array([V_hi, r_hi]),
        )

    @property
    def n_rules(self) -> int:
        return int(self.A.shape[0])

    def premise(self, v_x: ArrayLike, r: ArrayLike) -> FloatArray:
        """xi = [1/v_x, r] of eq. (15), shape (..., 2)."""
        return np.stack([1.0 / np.asarray(v_x, dtype=float), np.asarray(r, dtype=float)], axis=-1)

    def in_domain(self, xi: ArrayLike) -> np.ndarray:
        """True where the premise lies in the design box, shape (...)."""
        xi = np.asarray(xi, dtype=float)
        inside = (xi >= self.premise_low) & (xi <= self.premise_high)
        return np.asarray(np.all(inside, axis=-1))

    def clip_premise(self, xi: ArrayLike) -> FloatArray:
        """The premise clipped to the design box, shape (..., 2)."""
        return np.clip(np.asarray(xi, dtype=float), self.premise_low, self.premise_high)

    def memberships(self, xi: ArrayLike) -> FloatArray:
        """h_i(xi) of eq. (16). Inside the box they lie on the simplex.

        Parameters
        ----------
        xi : (..., 2) array_like
            The premise [1/v_x [s/m], r [rad/s]].

        Returns
        -------
        (..., 4) ndarray
            The rules' memberships.
        """
        xi = np.asarray(xi, dtype=float)
        wV = sector_weights(xi[..., 0], self.premise_low[0], self.premise_high[0])
        wr = sector_weights(xi[..., 1], self.premise_low[1], self.premise_high[1])
        return np.stack([wV[a] * wr[b] for a, b in RULE_CORNERS], axis=-1)

    def g(self, v_x: ArrayLike, r: ArrayLike) -> FloatArray:
        """The measured nonlinear consequent g(xi) of eq. (15), corrected.

        Parameters
        ----------
        v_x : array_like
            Longitudinal speed [m/s], shape (...).
        r : array_like
            Yaw rate [rad/s], shape (...).

        Returns
        -------
        (..., 3) ndarray
            g [m/s, m/s, rad/s] per sample.
        """
        k = self.params.symbols()
        s = k["s"]
        v_x = np.asarray(v_x, dtype=float)
        r = np.asarray(r, dtype=float)
        # g_1 = -s (C_x v_x^2 + F_r) / m_eff
        g1 = -s * (k["C_x"] * v_x**2 + k["F_r"]) / k["m_eff"]
        # g_2 = s (2 (C_r l_r - C_f l_f) / (M_v v_x) - v_x) r
        g2 = s * (2.0 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / (k["M_v"] * v_x) - v_x) * r
        # g_3 = -s 2 (C_f l_f^2 + C_r l_r^2) / (I_z v_x) r
        g3 = -s * 2.0 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / (k["I_z"] * v_x) * r
        return np.stack([g1, g2, g3], axis=-1)

    @staticmethod
    def phi(x: ArrayLike) -> FloatArray:
        """The unmeasured nonlinearity phi(x) = v_y^2, shape (...)."""
        x = np.asarray(x, dtype=float)
        return np.asarray(x[..., 1] ** 2)

    @property
    def has_cornering_drag(self) -> bool:
        return bool(np.any(self.G_c))

    def phi_c(self, x: ArrayLike, steer_rad: ArrayLike) -> FloatArray:
        """The cornering drag phi_c = F_yf sin(delta) [N] of the applied road-wheel angle.

        F_yf = 2 C_f (delta - (v_y + l_f r) / v_x) of eq. (2). Enters through G_c (zero without cornering drag).

        Parameters
        ----------
        x : (..., 3) array_like
            State [v_x [m/s], v_y [m/s], r [rad/s]].
        steer_rad : (...) array_like
            Applied delta = delta_d + b_delta delta_f [rad].

        Returns
        -------
        (...) ndarray
            phi_c [N].
        """
        x = np.asarray(x, dtype=float)
        k = self.params.symbols()
        delta = np.asarray(steer_rad, dtype=float)
        # phi_c = F_yf sin(delta), F_yf = 2 C_f (delta - (v_y + l_f r) V_x)
        F_yf = 2.0 * k["C_f"] * (delta - (x[..., 1] + k["l_f"] * x[..., 2]) / x[..., 0])
        return np.asarray(F_yf * np.sin(delta))

    def step(self, x: ArrayLike, u_d: ArrayLike, w: ArrayLike, f: ArrayLike) -> FloatArray:
        """x_{k+1} of eq. (15); equals the Euler step (12) inside S_x.

        With the cornering drag: + G_c phi_c(x, delta_d + b_delta delta_f).

        Parameters
        ----------
        x, u_d, w, f : array_like
            State, demand, wind force and faults, as for :func:`synth.model.continuous_dynamics`.

        Returns
        -------
        (..., 3) ndarray
            x_{k+1}.
        """
        x = np.asarray(x, dtype=float)
        u_d = np.asarray(u_d, dtype=float)
        f = np.asarray(f, dtype=float)
        h = self.memberships(self.premise(x[..., 0], x[..., 2]))
        Ax = np.einsum("...i,ijk,...k->...j", h, self.A, x)
        nxt = (
            Ax
            + u_d @ self.B.T
            + np.asarray(w, dtype=float)[..., None] * self.D[:, 0]
            + f @ self.F.T
            + self.g(x[..., 0], x[..., 2])
            + self.phi(x)[..., None] * self.G[:, 0]
        )
        if self.has_cornering_drag:
            steer = u_d[..., 1] + self.params.steer_fault_gain * f[..., 1]
            nxt = nxt + self.phi_c(x, steer)[..., None] * self.G_c[:, 0]
        return nxt


def _vertex_matrix(V_x: float, r: float, p: VehicleParams) -> FloatArray:
    """A(V_x, r) of eq. (15) at one premise point, shape (3, 3)."""
    k = p.symbols()
    s = k["s"]
    return np.array(
        [
            [1.0, s * r, 0.0],
            [0.0, 1.0 - s * 2.0 * (k["C_f"] + k["C_r"]) / k["M_v"] * V_x, 0.0],
            [0.0, s * 2.0 * (k["l_r"] * k["C_r"] - k["C_f"] * k["l_f"]) / k["I_z"] * V_x, 1.0],
        ]
    )


@dataclass(frozen=True)
class ConventionalTSModel(DiscreteTSModel):
    """The conventional 8-rule TS model of eq. (14), premise varpi = [v_x, 1/v_x, v_y].

    A : (8, 3, 3)  A_i = I + s A_v at the corners of the premise box, rule index
                   i = 4 a + 2 b + c for corner (v_x, 1/v_x, v_y) = (a, b, c), 0 = low.
    """

    C: FloatArray
    premise_low: FloatArray
    premise_high: FloatArray

    @classmethod
    def build(cls, params: VehicleParams, bounds: OperatingBounds) -> ConventionalTSModel:
        """Build the 8 vertex matrices at the corners of the premise box [v_x, 1/v_x, v_y].

        Parameters
        ----------
        params : VehicleParams
            The vehicle, with the paper's longitudinal equation.
        bounds : OperatingBounds
            The operating box.

        Returns
        -------
        ConventionalTSModel
            The model of eq. (14).

        Raises
        ------
        BadParameters
            The vehicle has rolling resistance or cornering drag, which eq. (14) does not model.
        """
        if params.rolling_resistance_n != 0.0 or params.cornering_drag:
            raise BadParameters(
                "the conventional model of eq. (14) has the paper's longitudinal equation: no rolling resistance "
                "and no cornering drag"
            )
        low = np.array([bounds.vx_min_mps, 1.0 / bounds.vx_max_mps, bounds.vy_min_mps])
        high = np.array([bounds.vx_max_mps, 1.0 / bounds.vx_min_mps, bounds.vy_max_mps])
        corners = [np.where(np.array(c) == 1, high, low) for c in itertools.product((0, 1), repeat=3)]
        A = np.stack([_affine_state_matrix(float(v_x), float(inv), float(v_y), params) for v_x, inv, v_y in corners])
        return cls(
            params=params,
            bounds=bounds,
            A=A,
            **euler_input_matrices(params),
            C=C.copy(),
            premise_low=low,
            premise_high=high,
        )

    def memberships(self, varpi: ArrayLike) -> FloatArray:
        """h_i(varpi), shape (..., 8): products of the three sector weights."""
        varpi = np.asarray(varpi, dtype=float)
        weights = [sector_weights(varpi[..., j], self.premise_low[j], self.premise_high[j]) for j in range(3)]
        return np.stack(
            [weights[0][a] * weights[1][b] * weights[2][c] for a, b, c in itertools.product((0, 1), repeat=3)],
            axis=-1,
        )

    def step(self, x: ArrayLike, u_d: ArrayLike, w: ArrayLike, f: ArrayLike) -> FloatArray:
        """x_{k+1} of eq. (14).

        Parameters
        ----------
        x, u_d, w, f : array_like
            As for :meth:`NTSModel.step`.

        Returns
        -------
        (..., 3) ndarray
            x_{k+1}.
        """
        x = np.asarray(x, dtype=float)
        varpi = np.stack([x[..., 0], 1.0 / x[..., 0], x[..., 1]], axis=-1)
        h = self.memberships(varpi)
        Ax = np.einsum("...i,ijk,...k->...j", h, self.A, x)
        return (
            Ax
            + np.asarray(u_d, dtype=float) @ self.B.T
            + np.asarray(w, dtype=float)[..., None] * self.D[:, 0]
            + np.asarray(f, dtype=float) @ self.F.T
        )


def _affine_state_matrix(v_x: float, inv_v_x: float, v_y: float, p: VehicleParams) -> FloatArray:
    """I + s A_v(x) with v_x, 1/v_x and v_y treated as independent premises, shape (3, 3)."""
    k = p.symbols()
    s = k["s"]
    a11 = -k["C_x"] * v_x / k["m_eff"]
    a22 = -2.0 * (k["C_f"] + k["C_r"]) / k["M_v"] * inv_v_x - k["C_y"] * v_y / k["M_v"]
    a23 = 2.0 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / k["M_v"] * inv_v_x - v_x
    a32 = 2.0 * (k["l_r"] * k["C_r"] - k["C_f"] * k["l_f"]) / k["I_z"] * inv_v_x
    a33 = -2.0 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / k["I_z"] * inv_v_x
    A_v = np.array([[a11, 0.0, v_y], [0.0, a22, a23], [0.0, a32, a33]])
    return np.eye(3) + s * A_v

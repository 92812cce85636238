"""The LMIs of Theorem 2 (eqs. 33-44), built with cvxpy.

Decision variables (design coordinates, see :class:`DesignCoordinates`):
P_i (fuzzy Lyapunov matrices, or one common P), the slack R, X_i = R H_i
(eq. 40) and either W = R E (no decoupling: E free) or Z = R Y (eq. 41,
exact decoupling: E = U + Y V). With Psi = R M (eq. 35) the LMI of eq. (33),
with the decay rate alpha of the bisection, reads for every rule i, next rule
j and DMVT vertex rho:

    [[alpha^2 P_i,                   *        ],
     [Psi A(i, rho) - X_i C_bar,  R + R^T - P_j]]  >  0,           (33)

    A(i, rho) = A_bar_i + sum_k rho_k G_k c_k^T.                   (34)

The paper has one DMVT scalar, rho = d(v_y^2)/dv_y with G_k = G_bar and
c_k = e_vy; the cornering drag adds two (synth.augmented.AugmentedModel.dmvt_terms).

Pre- and post-multiplying by [I, -N^T] gives N^T P_j N < alpha^2 P_i (eq. 30).

Two equivalent forms are offered:

* ``vertex``: the paper's 4 x 4 x 2 = 32 LMIs of size 2n (2^K rho vertices
  per rule pair with K DMVT scalars).
* ``petersen``: the LMI is affine in each rho_k, which enters through the
  rank-one term Psi G_k c_k^T, so by Petersen's lemma (lossless for one
  scalar uncertainty) the rho-vertices of each (i, j) collapse into one LMI
  of size 2n + K with a multiplier lambda_k,ij > 0 per scalar:

      [[L0_ij - sum_k lambda_k b_k b_k^T, a_1 .. a_K], [a^T, diag(lambda)]] > 0,
      a_k = [0; radius_k Psi G_k],  b_k = [c_k; 0],

  where L0_ij is the vertex LMI at the centre of the rho box. For the paper
  (K = 1) 16 LMIs instead of 32 and no loss: the solver's KKT system is much
  smaller (docs/benchmarks/synthesis.md). With K > 1 the form is sufficient,
  not necessary.

When the yaw-rate bounds are symmetric, either form is posed on the
mirror-invariant points only (:mod:`synth.symmetry`): half the LMIs, no loss.

Every solution is re-checked in numpy against the vertex LMIs of the
paper's form (32 for the paper's model), whichever form was solved
(:mod:`synth.certificate`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import cvxpy as cp
import numpy as np

from synth.augmented import AugmentedModel, DMVTTerm, difference_coordinates, dmvt_vertices
from synth.errors import BadParameters, SolverFailed
from synth.existence import decoupling_matrices
from synth.model import FloatArray
from synth.solver import SolveInfo, solve
from synth.symmetry import MirrorSymmetry, Parametrisation, find_mirror_symmetry

LyapunovKind = Literal["fuzzy", "common"]
LMIForm = Literal["vertex", "petersen"]

#: Scale of the torque-fault components in the design coordinates: one design
#: unit is this many N m. b_T s / I_e ~ 2e-5 otherwise leaves the fault chain
#: badly conditioned (NOTES.md, finding 2).
DEFAULT_TORQUE_FAULT_SCALE = 1.0e4


@dataclass(frozen=True)
class DesignCoordinates:
    """The augmented model in the solver's coordinates x' = T x_bar.

    T     : (n, n) change of basis (difference coordinates, then scaling)
    T_inv : (n, n)
    A     : (r, n, n) T A_bar_i T^-1
    C     : (p, n) C_bar T^-1
    D     : (n, 1) T D_bar
    terms : the DMVT terms (synth.augmented.DMVTTerm) with G' = T G and c'^T = c^T T^-1:
            Delta phi = sum_k rho_k G'_k c'_k^T e'
    """

    T: FloatArray
    T_inv: FloatArray
    A: FloatArray
    C: FloatArray
    D: FloatArray
    terms: tuple[DMVTTerm, ...]

    @property
    def n(self) -> int:
        return int(self.A.shape[1])

    @property
    def n_rules(self) -> int:
        return int(self.A.shape[0])

    def A_at(self, i: int, rho: tuple[float, ...]) -> FloatArray:
        """A(i, rho) of eq. (34), shape (n, n): A_i + sum_k rho_k G_k c_k^T."""
        A = self.A[i].copy()
        for value, term in zip(rho, self.terms, strict=True):
            A += value * term.matrix()
        return A

    def A_centre(self, i: int) -> FloatArray:
        """A(i, rho) at the centre of the rho box, shape (n, n)."""
        return self.A_at(i, tuple(term.centre for term in self.terms))

    def vertices(self) -> list[tuple[float, ...]]:
        """Every vertex of the rho box (synth.augmented.dmvt_vertices)."""
        return dmvt_vertices(self.terms)

    def petersen_columns(self, left: cp.Expression | FloatArray) -> tuple[list[cp.Expression], list[FloatArray]]:
        """(a_k, b_k) of the Petersen form for ``left`` (the R or Psi that multiplies A(i, rho) in the LMI).

        The rho_k part of the LMI's lower-left block is rho_k left G_k c_k^T about the centre; for
        t_k in [-1, 1] it is t_k (a_k b_k^T + b_k a_k^T) with a_k = [0; radius_k left G_k] and
        b_k = [c_k^T; 0] (top block n rows, lower block n rows).
        """
        n = self.n
        zeros = np.zeros((n, 1))
        a = [cp.vstack([zeros, term.radius * (left @ term.G)]) for term in self.terms]
        b = [np.vstack([term.row.T, zeros]) for term in self.terms]
        return a, b

    def mirror_symmetry(self) -> MirrorSymmetry | None:
        """The left-right mirror of the data in these coordinates, if they have it (synth.symmetry)."""
        return find_mirror_symmetry(
            self.T, self.T_inv, self.A, self.C, [(term.matrix(), term.centre) for term in self.terms]
        )


def design_coordinates(
    aug: AugmentedModel,
    *,
    difference: bool = True,
    torque_fault_scale: float = DEFAULT_TORQUE_FAULT_SCALE,
    state_scales: FloatArray | None = None,
) -> DesignCoordinates:
    """The solver coordinates: difference coordinates for the fault chain, then a diagonal scaling.

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model.
    difference : bool, default True
        Use the difference coordinates of the fault chain (else shift coordinates).
    torque_fault_scale : float
        The unit of the torque-fault components [N m]; by default only they are scaled.
    state_scales : (n,) ndarray, optional
        The unit of every coordinate instead.

    Returns
    -------
    DesignCoordinates
        T, T_inv and the model's matrices in the new coordinates.

    Raises
    ------
    BadParameters
        A scale is not positive and finite, or ``state_scales`` has the wrong length.
    """
    if not np.isfinite(torque_fault_scale) or torque_fault_scale <= 0:
        raise BadParameters(f"torque_fault_scale must be positive and finite, got {torque_fault_scale!r}")
    n = aug.n
    basis = difference_coordinates(aug.fault_order) if difference else np.eye(n)
    if state_scales is None:
        scale = np.ones(n)
        scale[3::2] = torque_fault_scale  # every torque-fault component of the chain
    else:
        scale = np.asarray(state_scales, dtype=float)
        if scale.shape != (n,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise BadParameters(f"state_scales must be {n} positive finite numbers, got {state_scales!r}")
    T = np.diag(1.0 / scale) @ basis
    T_inv = np.linalg.inv(T)
    return DesignCoordinates(
        T=T,
        T_inv=T_inv,
        A=np.einsum("ab,ibc,cd->iad", T, aug.A_bar, T_inv),
        C=aug.C_bar @ T_inv,
        D=T @ aug.D_bar,
        terms=tuple(term.transformed(T, T_inv) for term in aug.dmvt_terms),
    )


@dataclass(frozen=True)
class LMISolution:
    """Values of the decision variables and the gains they define, design coordinates.

    P : (r or 1, n, n); R : (n, n); E : (n, p); H : (r, n, p)
    """

    P: FloatArray
    R: FloatArray
    E: FloatArray
    H: FloatArray
    alpha: float
    #: what the solver reported for this point
    info: SolveInfo


def gains_from_solution(
    dc: DesignCoordinates, E: FloatArray, H: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """M, N_i, L_i from E and H_i (eqs. 20, 43, 44), design coordinates.

    M = I + E C_bar; N_i = M A_bar_i - H_i C_bar; L_i = H_i (I + C_bar E) - M A_bar_i E.

    Parameters
    ----------
    dc : DesignCoordinates
        The design coordinates.
    E : (n, p) ndarray
        The observer's E.
    H : (r, n, p) ndarray
        H_i.

    Returns
    -------
    M : (n, n) ndarray
    N : (r, n, n) ndarray
    L : (r, n, p) ndarray
    """
    n = dc.n
    p = dc.C.shape[0]
    M = np.eye(n) + E @ dc.C
    # eq. (43)
    N = np.einsum("ab,ibc->iac", M, dc.A) - H @ dc.C
    # eq. (44)
    L = H @ (np.eye(p) + dc.C @ E) - np.einsum("ab,ibc,cd->iad", M, dc.A, E)
    return M, N, L


class Theorem2LMIs:
    """The LMI feasibility problem of Theorem 2, compiled once and re-solved per alpha."""

    def __init__(
        self,
        dc: DesignCoordinates,
        *,
        decoupled: bool,
        lyapunov: LyapunovKind = "fuzzy",
        form: LMIForm = "petersen",
        margin: float = 1e-4,
        use_symmetry: bool = True,
    ) -> None:
        if lyapunov not in ("fuzzy", "common"):
            raise BadParameters(f"lyapunov must be 'fuzzy' or 'common', got {lyapunov!r}")
        if form not in ("vertex", "petersen"):
            raise BadParameters(f"lmi_form must be 'vertex' or 'petersen', got {form!r}")
        self.dc = dc
        self.decoupled = decoupled
        self.lyapunov = lyapunov
        self.form = form
        self.margin = margin
        n, r = dc.n, dc.n_rules
        p = dc.C.shape[0]
        self.alpha_sq = cp.Parameter(nonneg=True, value=1.0, name="alpha_sq")
        n_P = r if lyapunov == "fuzzy" else 1
        # the decoupled design is refused before any solve for this plant; it is posed in full
        self.symmetry = dc.mirror_symmetry() if use_symmetry and not decoupled else None
        var = Parametrisation(self.symmetry)
        if lyapunov == "fuzzy":
            self.P = var.per_rule_square(n, r, "P", symmetric=True)
        else:
            self.P = [var.square(n, "P", symmetric=True)]
        self.R = var.square(n, "R")
        self.X = var.per_rule_gain(n, p, r, "X")
        if decoupled:
            U, V = _decoupling_in(dc)
            self.U, self.V = U, V
            self.Z = cp.Variable((n, p), name="Z")
            # eq. (35): Psi = R + (R U + Z V) C_bar
            RE = self.R @ U + self.Z @ V
        else:
            self.W = var.gain(n, p, "W")
            RE = self.W
        self.RE = RE
        Psi = self.R + RE @ dc.C
        sym_R = self.R + self.R.T
        constraints: list[cp.Constraint] = []
        eye_n = np.eye(n)
        distinct_P = var.representatives(n_P) if lyapunov == "fuzzy" else [0]
        for k in distinct_P:
            constraints += [self.P[k] >> margin * eye_n]
        constraints.append(sum(cp.trace(P_i) for P_i in self.P) <= n * n_P)
        self.multipliers: list[cp.Variable] = []
        for i, j in var.pairs(r, n_P):
            P_i = self.P[i if lyapunov == "fuzzy" else 0]
            P_j = self.P[j]
            if form == "vertex":
                for rho in dc.vertices():
                    Q = Psi @ dc.A_at(i, rho) - self.X[i] @ dc.C
                    # symmetric by construction: cvxpy's PSD constraint reads one triangle
                    block = cp.bmat([[self.alpha_sq * P_i, Q.T], [Q, sym_R - P_j]])
                    constraints.append(block >> margin * np.eye(2 * n))
            else:
                Q0 = Psi @ dc.A_centre(i) - self.X[i] @ dc.C
                L0 = cp.bmat([[self.alpha_sq * P_i, Q0.T], [Q0, sym_R - P_j]])
                a, b = dc.petersen_columns(Psi)
                block, lams = petersen_block(L0, a, [b_k @ b_k.T for b_k in b], f"lambda_{i + 1}{j + 1}")
                self.multipliers.extend(lams)
                constraints.append(block >> margin * np.eye(2 * n + len(a)))
        self.n_lmis = len(constraints) - len(distinct_P) - 1
        started = time.perf_counter()
        self.problem = cp.Problem(cp.Minimize(0), constraints)
        self.build_time_s = time.perf_counter() - started

    def solve(self, alpha: float, solver: str, time_limit_s: float = 60.0) -> LMISolution:
        """Solve at decay rate ``alpha``; raise :class:`SolverFailed` saying why there is no point."""
        self.alpha_sq.value = alpha**2
        info = solve(self.problem, solver, time_limit_s)
        if self.R.value is None:
            raise SolverFailed(f"{solver} returned no value for the slack matrix R (status {info.status})")
        R = np.asarray(self.R.value)
        try:
            R_inv_RE = np.linalg.solve(R, np.asarray(self.RE.value))
            H = np.stack([np.linalg.solve(R, np.asarray(X_i.value)) for X_i in self.X])
        except np.linalg.LinAlgError as exc:
            raise SolverFailed(f"{solver} returned a singular slack matrix R") from exc
        # decoupled: E = R^-1 (R U + Z V) = U + Y V with Y = R^-1 Z (eqs. 37, 41)
        return LMISolution(
            P=np.stack([np.asarray(P_i.value) for P_i in self.P]),
            R=R,
            E=R_inv_RE,
            H=H,
            alpha=alpha,
            info=info,
        )


def petersen_block(
    L0: cp.Expression, a: list[cp.Expression], bbT: list[FloatArray | cp.Expression], name: str
) -> tuple[cp.Expression, list[cp.Variable]]:
    """[[L0 - sum_k lambda_k b_k b_k^T, a_1 .. a_K], [a_k^T, diag(lambda)]] and the lambda_k.

    Petersen's lemma: for one term (K = 1) this is positive definite for some lambda > 0 exactly when
    L0 + t (a b^T + b a^T) > 0 for every t in [-1, 1], i.e. the LMI at both ends of the scalar uncertainty that
    a b^T carries (rho about the centre of its interval). For several independent scalars t_k in [-1, 1] the same
    block with one multiplier each is sufficient (completing the square term by term), not necessary; the numpy
    verification checks every vertex regardless.

    Parameters
    ----------
    L0 : cvxpy.Expression
        The LMI at the centre of the box of rho.
    a : list of cvxpy.Expression
        The a_k columns.
    bbT : list of ndarray or cvxpy.Expression
        The outer products b_k b_k^T (constants, or parameters of a problem compiled once per structure).
    name : str
        The multipliers' name.

    Returns
    -------
    block : cvxpy.Expression
        The Petersen block, symmetric by construction when L0 and the b_k b_k^T are (cvxpy's PSD constraint
        reads one triangle, so a symmetrised copy would only double what it compiles).
    multipliers : list of cvxpy.Variable
        lambda_k.
    """
    lams = [cp.Variable(name=f"{name}_{k + 1}" if len(a) > 1 else name) for k in range(len(a))]
    top_left = L0
    for lam, bbT_k in zip(lams, bbT, strict=True):
        top_left = top_left - lam * bbT_k
    diag = cp.diag(cp.hstack(lams)) if len(lams) > 1 else cp.reshape(lams[0], (1, 1), order="C")
    block = cp.bmat([[top_left, cp.hstack(a)], [cp.hstack(a).T, diag]])
    return block, lams


def _decoupling_in(dc: DesignCoordinates) -> tuple[FloatArray, FloatArray]:
    """U, V of eqs. (38)-(39) in design coordinates."""
    CD = dc.C @ dc.D
    CD_pinv = np.linalg.pinv(CD)
    return -dc.D @ CD_pinv, np.eye(CD.shape[0]) - CD @ CD_pinv


__all__ = [
    "DEFAULT_TORQUE_FAULT_SCALE",
    "DesignCoordinates",
    "LMISolution",
    "Theorem2LMIs",
    "decoupling_matrices",
    "design_coordinates",
    "gains_from_solution",
    "petersen_block",
]

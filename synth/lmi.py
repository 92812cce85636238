"""The LMIs of Theorem 2 (eqs. 33-44), built with cvxpy.

Decision variables (design coordinates, see :class:`DesignCoordinates`):
P_i (fuzzy Lyapunov matrices, or one common P), the slack R, X_i = R H_i
(eq. 40) and either W = R E (no decoupling: E free) or Z = R Y (eq. 41,
exact decoupling: E = U + Y V). With Psi = R M (eq. 35) the LMI of eq. (33),
with the decay rate alpha of the bisection, reads for every rule i, next rule
j and DMVT vertex rho:

    [[alpha^2 P_i,                   *        ],
     [Psi A(i, rho) - X_i C_bar,  R + R^T - P_j]]  >  0,           (33)

    A(i, rho) = A_bar_i + G_bar rho_row(rho).                      (34)

Pre- and post-multiplying by [I, -N^T] gives N^T P_j N < alpha^2 P_i (eq. 30).

Two equivalent forms are offered:

* ``vertex``: the paper's 4 x 4 x 2 = 32 LMIs of size 2n.
* ``petersen``: the LMI is affine in the scalar rho and rho enters through the
  rank-one term Psi G_bar rho_row, so by Petersen's lemma (lossless for one
  scalar uncertainty) the two rho-vertices of each (i, j) collapse into one LMI
  of size 2n + 1 with a multiplier lambda_ij > 0:

      [[L0_ij - lambda b b^T, a], [a^T, lambda]] > 0,
      a = [0; rho_rad Psi G_bar],  b = [rho_row^T; 0],

  where L0_ij is the vertex LMI at the centre of S_rho. 16 LMIs instead of 32:
  the solver's KKT system is much smaller (docs/benchmarks/synthesis.md).

When the yaw-rate bounds are symmetric, either form is posed on the
mirror-invariant points only (:mod:`synth.symmetry`): half the LMIs, no loss.

Every solution is re-checked in numpy against the 32 vertex LMIs of the
paper's form, whichever form was solved (:mod:`synth.certificate`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import cvxpy as cp
import numpy as np

from synth.augmented import VY_INDEX, AugmentedModel, difference_coordinates
from synth.errors import BadParameters
from synth.existence import decoupling_matrices
from synth.model import FloatArray
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
    G     : (n, 1) T G_bar
    D     : (n, 1) T D_bar
    rho_row : (1, n) e_vy^T T^-1: Delta phi = rho * rho_row e'
    rho_low, rho_high : bounds of rho = d phi / d v_y [m/s]
    """

    T: FloatArray
    T_inv: FloatArray
    A: FloatArray
    C: FloatArray
    G: FloatArray
    D: FloatArray
    rho_row: FloatArray
    rho_low: float
    rho_high: float

    @property
    def n(self) -> int:
        return int(self.A.shape[1])

    @property
    def n_rules(self) -> int:
        return int(self.A.shape[0])

    def rho_vertices(self) -> tuple[float, float]:
        return self.rho_low, self.rho_high

    def A_rho(self, i: int, rho: float) -> FloatArray:
        """A(i, rho) of eq. (34), shape (n, n)."""
        return self.A[i] + rho * self.G @ self.rho_row

    def mirror_symmetry(self) -> MirrorSymmetry | None:
        """The left-right mirror of the data in these coordinates, if they have it (synth.symmetry)."""
        return find_mirror_symmetry(self.T, self.T_inv, self.A, self.C, self.G @ self.rho_row)


def design_coordinates(
    aug: AugmentedModel,
    *,
    difference: bool = True,
    torque_fault_scale: float = DEFAULT_TORQUE_FAULT_SCALE,
    state_scales: FloatArray | None = None,
) -> DesignCoordinates:
    """The solver coordinates: difference coordinates for the fault chain, then a diagonal scaling.

    By default only the torque-fault components are scaled (by ``torque_fault_scale``);
    ``state_scales`` (n,) sets the unit of every coordinate instead.
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
    e_vy = np.zeros((1, n))
    e_vy[0, VY_INDEX] = 1.0
    rho_low, rho_high = aug.rho_vertices()
    return DesignCoordinates(
        T=T,
        T_inv=T_inv,
        A=np.einsum("ab,ibc,cd->iad", T, aug.A_bar, T_inv),
        C=aug.C_bar @ T_inv,
        G=T @ aug.G_bar,
        D=T @ aug.D_bar,
        rho_row=e_vy @ T_inv,
        rho_low=float(rho_low),
        rho_high=float(rho_high),
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
    solver: str
    status: str
    iterations: int | None
    solve_time_s: float
    extra: dict[str, float] = field(default_factory=dict)


def gains_from_solution(
    dc: DesignCoordinates, E: FloatArray, H: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """M, N_i, L_i from E and H_i (eqs. 20, 43, 44), design coordinates.

    M = I + E C_bar; N_i = M A_bar_i - H_i C_bar; L_i = H_i (I + C_bar E) - M A_bar_i E.
    Returns M (n, n), N (r, n, n), L (r, n, p).
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
        rho_lo, rho_hi = dc.rho_vertices()
        for i, j in var.pairs(r, n_P):
            P_i = self.P[i if lyapunov == "fuzzy" else 0]
            P_j = self.P[j]
            if form == "vertex":
                for rho in (rho_lo, rho_hi):
                    Q = Psi @ dc.A_rho(i, rho) - self.X[i] @ dc.C
                    block = cp.bmat([[self.alpha_sq * P_i, Q.T], [Q, sym_R - P_j]])
                    constraints.append(_sym(block) >> margin * np.eye(2 * n))
            else:
                rho_mid, rho_rad = 0.5 * (rho_lo + rho_hi), 0.5 * (rho_hi - rho_lo)
                Q0 = Psi @ dc.A_rho(i, rho_mid) - self.X[i] @ dc.C
                L0 = cp.bmat([[self.alpha_sq * P_i, Q0.T], [Q0, sym_R - P_j]])
                b = np.vstack([dc.rho_row.T, np.zeros((n, 1))])
                a = cp.vstack([np.zeros((n, 1)), rho_rad * (Psi @ dc.G)])
                block, lam = petersen_block(L0, a, b, f"lambda_{i + 1}{j + 1}")
                self.multipliers.append(lam)
                constraints.append(block >> margin * np.eye(2 * n + 1))
        self.n_lmis = len(constraints) - len(distinct_P) - 1
        started = time.perf_counter()
        self.problem = cp.Problem(cp.Minimize(0), constraints)
        self.build_time_s = time.perf_counter() - started

    def solve(self, alpha: float, solver: str, time_limit_s: float = 60.0) -> LMISolution | str:
        """Solve at decay rate ``alpha``: the solution, or why the solver gave none."""
        self.alpha_sq.value = alpha**2
        options = {**_SOLVER_OPTIONS.get(solver, {}), _TIME_LIMIT_OPTION[solver]: time_limit_s}
        started = time.perf_counter()
        try:
            self.problem.solve(solver=solver, **options)
        except cp.error.SolverError as exc:
            return f"{solver} stopped without a solution ({str(exc).split('.')[0]})"
        elapsed = time.perf_counter() - started
        status = str(self.problem.status)
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or self.R.value is None:
            return f"{solver} status {status}"
        R = np.asarray(self.R.value)
        try:
            R_inv_RE = np.linalg.solve(R, np.asarray(self.RE.value))
            H = np.stack([np.linalg.solve(R, np.asarray(X_i.value)) for X_i in self.X])
        except np.linalg.LinAlgError:
            return f"{solver} returned a singular slack matrix R"
        # decoupled: E = R^-1 (R U + Z V) = U + Y V with Y = R^-1 Z (eqs. 37, 41)
        E = R_inv_RE
        stats = self.problem.solver_stats
        return LMISolution(
            P=np.stack([np.asarray(P_i.value) for P_i in self.P]),
            R=R,
            E=E,
            H=H,
            alpha=alpha,
            solver=solver,
            status=status,
            iterations=stats.num_iters if stats is not None else None,
            solve_time_s=elapsed,
            extra={
                "compile_s": float(self.problem.compilation_time or 0.0),
                "solver_s": float(stats.solve_time or 0.0) if stats is not None else float("nan"),
            },
        )


def petersen_block(L0: cp.Expression, a: cp.Expression, b: FloatArray, name: str) -> tuple[cp.Expression, cp.Variable]:
    """[[L0 - lambda b b^T, a], [a^T, lambda]] (symmetrised) and its multiplier lambda.

    Petersen's lemma: this is positive definite for some lambda > 0 exactly when
    L0 + t (a b^T + b a^T) > 0 for every t in [-1, 1], i.e. the LMI at both ends of
    the scalar uncertainty that a b^T carries (here rho about the centre of S_rho).
    """
    lam = cp.Variable(name=name)
    block = cp.bmat([[L0 - lam * (b @ b.T), a], [a.T, cp.reshape(lam, (1, 1), order="C")]])
    return _sym(block), lam


def _sym(block: cp.Expression) -> cp.Expression:
    return 0.5 * (block + block.T)


def _decoupling_in(dc: DesignCoordinates) -> tuple[FloatArray, FloatArray]:
    """U, V of eqs. (38)-(39) in design coordinates."""
    CD = dc.C @ dc.D
    CD_pinv = np.linalg.pinv(CD)
    return -dc.D @ CD_pinv, np.eye(CD.shape[0]) - CD @ CD_pinv


#: Solver settings: Clarabel on one thread with chordal decomposition (fastest
#: here), SCS at a tight tolerance as the fallback (its default tolerance
#: returned unstable "optimal" gains, NOTES.md finding 3).
_SOLVER_OPTIONS: dict[str, dict[str, object]] = {
    "CLARABEL": {"max_threads": 1},
    "SCS": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 200_000},
}
_TIME_LIMIT_OPTION = {"CLARABEL": "time_limit", "SCS": "time_limit_secs"}

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

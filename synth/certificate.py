"""Independent numpy verification of a design and the certificate that records it.

Never trust a solver status (NOTES.md, finding 3). Whatever LMI form was
solved, a design is accepted only if, recomputed in numpy from the gains
(N_i, M) and the multipliers (P_i, R):

1. every P_i is positive definite;
2. every vertex LMI of eq. (33) (rule i, next rule j, DMVT vertex rho) has a
   positive minimum eigenvalue at the claimed decay rate; by convexity this
   proves N(h, rho)^T P(h+) N(h, rho) < alpha^2 P(h) for all h, h+, rho;
3. the spectral radius of N(h) + M G_bar rho_row(rho) over a dense grid of the
   premise box and of S_rho stays below the certified decay rate (a
   consequence of 2 at h+ = h, so a cross-check of the algebra).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import scipy.linalg

from synth.errors import VerificationFailed
from synth.fuzzy import NTSModel
from synth.model import FloatArray

#: Relative threshold above which a minimum eigenvalue counts as positive.
STRICT_TOL = 1e-10
#: Grid of the verification: points per premise axis and per rho axis.
GRID_POINTS_PER_AXIS = 41
GRID_RHO_POINTS = 9


@dataclass(frozen=True)
class VerificationReport:
    """What the numpy check found, design coordinates for the LMIs.

    lmi_min_eigenvalues : one per vertex LMI (i, j, rho), in that order
    """

    lmi_min_eigenvalues: list[float]
    P_min_eigenvalues: list[float]
    slack_min_eigenvalue: float
    certified_decay_rate: float
    spectral_radius_max: float
    spectral_radius_at: dict[str, float]
    grid_points: int


def vertex_lmi(P_i: FloatArray, P_j: FloatArray, R: FloatArray, N_rho: FloatArray, alpha: float) -> FloatArray:
    """[[alpha^2 P_i, (R N)^T], [R N, R + R^T - P_j]] of eq. (33), shape (2n, 2n)."""
    RN = R @ N_rho
    top = np.hstack([alpha**2 * P_i, RN.T])
    bottom = np.hstack([RN, R + R.T - P_j])
    block = np.vstack([top, bottom])
    return 0.5 * (block + block.T)


def verify_lyapunov(
    N: FloatArray,
    MG_row: FloatArray,
    P: FloatArray,
    R: FloatArray,
    rho_vertices: tuple[float, float],
    alpha: float,
) -> tuple[list[float], list[float], float, float]:
    """Checks 1 and 2. Returns (LMI min eigenvalues, P min eigenvalues, slack min eig, certified alpha).

    N : (r, n, n); MG_row : (n, n), the rank-one term M G_bar rho_row per unit rho;
    P : (r or 1, n, n); R : (n, n).
    """
    r = N.shape[0]
    P_of = (lambda k: P[k]) if P.shape[0] == r else (lambda k: P[0])
    n_P = P.shape[0]
    P_min = [float(np.linalg.eigvalsh(0.5 * (P_k + P_k.T))[0]) for P_k in P]
    slack_min = min(float(np.linalg.eigvalsh(R + R.T - P_k)[0]) for P_k in P)
    lmi_min: list[float] = []
    alpha_sq_needed = 0.0
    for i in range(r):
        for j in range(n_P):
            S_j = R + R.T - P[j]
            for rho in rho_vertices:
                N_rho = N[i] + rho * MG_row
                block = vertex_lmi(P_of(i), P[j], R, N_rho, alpha)
                lmi_min.append(float(np.linalg.eigvalsh(block)[0]))
                if slack_min > 0 and min(P_min) > 0:
                    Q = R @ N_rho
                    lhs = Q.T @ np.linalg.solve(S_j, Q)
                    top = scipy.linalg.eigh(0.5 * (lhs + lhs.T), P_of(i), eigvals_only=True)[-1]
                    alpha_sq_needed = max(alpha_sq_needed, float(top))
    certified = float(np.sqrt(alpha_sq_needed)) if slack_min > 0 and min(P_min) > 0 else float("inf")
    return lmi_min, P_min, slack_min, certified


def spectral_radius_grid(
    nts: NTSModel,
    N: FloatArray,
    MG_row: FloatArray,
    rho_bounds: tuple[float, float],
    points_per_axis: int = GRID_POINTS_PER_AXIS,
    rho_points: int = GRID_RHO_POINTS,
) -> tuple[float, dict[str, float], int]:
    """Max spectral radius of N(h) + rho M G_bar rho_row over the premise box x S_rho.

    Returns (max, where it occurs as {speed_mps, yaw_rate_radps, rho}, number of points).
    """
    V = np.linspace(nts.premise_low[0], nts.premise_high[0], points_per_axis)
    r = np.linspace(nts.premise_low[1], nts.premise_high[1], points_per_axis)
    rho = np.linspace(rho_bounds[0], rho_bounds[1], rho_points)
    VV, rr, pp = np.meshgrid(V, r, rho, indexing="ij")
    h = nts.memberships(np.stack([VV.ravel(), rr.ravel()], axis=-1))
    stack = np.einsum("gi,ijk->gjk", h, N) + pp.ravel()[:, None, None] * MG_row
    radii = np.abs(np.linalg.eigvals(stack)).max(axis=-1)
    worst = int(np.argmax(radii))
    where = {
        "speed_mps": float(1.0 / VV.ravel()[worst]),
        "yaw_rate_radps": float(rr.ravel()[worst]),
        "rho": float(pp.ravel()[worst]),
    }
    return float(radii[worst]), where, int(radii.size)


def verify(
    nts: NTSModel,
    N_design: FloatArray,
    MG_row_design: FloatArray,
    P: FloatArray,
    R: FloatArray,
    rho_bounds: tuple[float, float],
    alpha: float,
    N_physical: FloatArray,
    MG_row_physical: FloatArray,
) -> VerificationReport:
    """Run checks 1-3; raise :class:`VerificationFailed` naming the first that fails.

    The LMIs are checked in the design coordinates (well conditioned); the
    spectral radius on the runtime gains in physical coordinates.
    """
    lmi_min, P_min, slack_min, certified = verify_lyapunov(N_design, MG_row_design, P, R, rho_bounds, alpha)
    radius, where, points = spectral_radius_grid(nts, N_physical, MG_row_physical, rho_bounds)
    report = VerificationReport(
        lmi_min_eigenvalues=lmi_min,
        P_min_eigenvalues=P_min,
        slack_min_eigenvalue=slack_min,
        certified_decay_rate=certified,
        spectral_radius_max=radius,
        spectral_radius_at=where,
        grid_points=points,
    )
    scale = max(1.0, float(np.abs(P).max()), float(np.abs(R).max()))
    details: dict[str, object] = {"report": asdict(report)}
    if min(P_min) <= STRICT_TOL * scale:
        raise VerificationFailed(
            f"a Lyapunov matrix P_i is not positive definite (min eigenvalue {min(P_min):.3e})", details
        )
    worst_lmi = min(lmi_min)
    if worst_lmi <= STRICT_TOL * scale:
        k = int(np.argmin(lmi_min))
        raise VerificationFailed(
            f"vertex LMI #{k + 1} of eq. (33) fails in numpy (min eigenvalue {worst_lmi:.3e} at alpha = {alpha:.4f})",
            details,
        )
    if not certified < 1.0:
        raise VerificationFailed(f"the certified decay rate {certified:.6f} is not below 1", details)
    if radius >= 1.0 or radius > certified + 1e-7:
        raise VerificationFailed(
            f"spectral radius {radius:.6f} of the error dynamics at v_x = {where['speed_mps']:.2f} m/s, "
            f"r = {where['yaw_rate_radps']:.3f} rad/s, rho = {where['rho']:.2f} exceeds the certified "
            f"decay rate {certified:.6f}",
            details,
        )
    return report


@dataclass(frozen=True)
class Certificate:
    """Everything needed to trust, reproduce and compare a design."""

    design: str
    fault_order: int
    lyapunov: str
    lmi_form: str
    decoupled: bool
    verified: bool
    decay_rate: float
    requested_decay_rate: float
    spectral_radius_max: float
    spectral_radius_at: dict[str, float]
    grid_points: int
    n_lmis_solved: int
    n_lmis_verified: int
    lmi_min_eigenvalue: float
    lmi_min_eigenvalues: list[float]
    P_min_eigenvalues: list[float]
    margin: float
    solver: str
    solver_version: str
    solver_status: str
    solver_iterations: int | None
    solves: int
    timings_s: dict[str, float]
    content_hash: str
    performance: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: "mirror": the LMIs were posed on mirror-invariant points only (synth.symmetry), "none": in full
    symmetry: str = "none"

    def summary(self) -> dict[str, Any]:
        """The headline figures, without the per-LMI lists."""
        data = asdict(self)
        data.pop("lmi_min_eigenvalues")
        data.pop("P_min_eigenvalues")
        return data


def content_hash(arrays: dict[str, FloatArray], meta: dict[str, Any]) -> str:
    """SHA-256 of the gain arrays (float64, C order) and the canonical JSON of ``meta``."""
    digest = hashlib.sha256()
    digest.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(arrays):
        digest.update(name.encode())
        digest.update(np.ascontiguousarray(arrays[name], dtype="<f8").tobytes())
    return digest.hexdigest()

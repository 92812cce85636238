"""Independent numpy verification of a design and the certificate that records it.

Never trust a solver status (NOTES.md, finding 3). Whatever LMI form was
solved, a design is accepted only if, recomputed in numpy from the gains
(N_i, M) and the multipliers (P_i, R):

1. every P_i is positive definite;
2. every vertex LMI of eq. (33) (rule i, next rule j, vertex of the box of
   the DMVT scalars rho_k) has a positive minimum eigenvalue at the claimed
   decay rate; by convexity this proves N(h, rho)^T P(h+) N(h, rho) < alpha^2 P(h)
   for all h, h+, rho;
3. the spectral radius of N(h) + sum_k rho_k M G_k c_k^T over a dense grid of
   the premise box and of the rho box stays below the certified decay rate (a
   consequence of 2 at h+ = h, so a cross-check of the algebra).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import scipy.linalg

from synth.augmented import DMVTTerm, dmvt_vertices
from synth.errors import VerificationFailed
from synth.fuzzy import NTSModel
from synth.model import FloatArray
from synth.options import DesignOptions
from synth.solver import SolveInfo, solver_version

#: Relative threshold above which a minimum eigenvalue counts as positive.
STRICT_TOL = 1e-10
#: Grid of the verification: points per premise axis and per rho axis.
GRID_POINTS_PER_AXIS = 41
GRID_RHO_POINTS = 9


@dataclass(frozen=True)
class VerificationReport:
    """What the numpy check found, design coordinates for the LMIs.

    lmi_min_eigenvalues : one per vertex LMI (i, j, rho vertex), in that order
    """

    lmi_min_eigenvalues: list[float]
    P_min_eigenvalues: list[float]
    slack_min_eigenvalue: float
    certified_decay_rate: float
    spectral_radius_max: float
    spectral_radius_at: dict[str, float]
    grid_points: int


def vertex_lmi(P_i: FloatArray, P_j: FloatArray, R: FloatArray, N_rho: FloatArray, alpha: float) -> FloatArray:
    """The vertex LMI of eq. (33), [[alpha^2 P_i, (R N)^T], [R N, R + R^T - P_j]].

    Parameters
    ----------
    P_i, P_j : (n, n) ndarray
        The Lyapunov matrices of rules i and j.
    R : (n, n) ndarray
        The slack matrix.
    N_rho : (n, n) ndarray
        The error dynamics at a vertex of rho, N_i + sum_k rho_k M G_k c_k^T.
    alpha : float
        The decay rate per sample.

    Returns
    -------
    (2n, 2n) ndarray
        The LMI's matrix, positive definite when the vertex is certified.
    """
    RN = R @ N_rho
    top = np.hstack([alpha**2 * P_i, RN.T])
    bottom = np.hstack([RN, R + R.T - P_j])
    block = np.vstack([top, bottom])
    return 0.5 * (block + block.T)


def error_term_matrices(terms: Sequence[DMVTTerm], M: FloatArray) -> list[FloatArray]:
    """M G_k c_k^T for every DMVT term: the error dynamics' change per unit rho_k (eqs. 27-28).

    Parameters
    ----------
    terms : sequence of DMVTTerm
        The DMVT terms of the augmented model.
    M : (n, n) ndarray
        The observer's M.

    Returns
    -------
    list of (n, n) ndarray
        One matrix per term.
    """
    return [term.matrix(M) for term in terms]


def verify_lyapunov(
    N: FloatArray,
    error_terms: Sequence[FloatArray],
    terms: Sequence[DMVTTerm],
    P: FloatArray,
    R: FloatArray,
    alpha: float,
) -> tuple[list[float], list[float], float, float]:
    """Checks 1 and 2 of the certificate: the vertex LMIs and P > 0.

    Every vertex of the box of rho is checked: the LMI is affine in rho, so the vertices prove it on the whole box.

    Parameters
    ----------
    N : (r, n, n) ndarray
        N_i.
    error_terms : sequence of (n, n) ndarray
        M G_k c_k^T per DMVT term (:func:`error_term_matrices`).
    terms : sequence of DMVTTerm
        The terms whose bounds give the box of rho.
    P : (r or 1, n, n) ndarray
        The Lyapunov matrices.
    R : (n, n) ndarray
        The slack matrix.
    alpha : float
        The decay rate per sample the LMIs were posed at.

    Returns
    -------
    lmi_min_eigenvalues : list of float
        The smallest eigenvalue of each vertex LMI.
    p_min_eigenvalues : list of float
        The smallest eigenvalue of each P_i.
    slack_min_eigenvalue : float
        The smallest eigenvalue of R + R^T - P_j over j.
    certified_alpha : float
        The smallest decay rate the LMIs certify (inf when P or R + R^T - P_j is not positive definite).
    """
    r = N.shape[0]
    P_of = (lambda k: P[k]) if P.shape[0] == r else (lambda k: P[0])
    n_P = P.shape[0]
    P_min = [float(np.linalg.eigvalsh(0.5 * (P_k + P_k.T))[0]) for P_k in P]
    slack_min = min(float(np.linalg.eigvalsh(R + R.T - P_k)[0]) for P_k in P)
    lmi_min: list[float] = []
    alpha_sq_needed = 0.0
    vertices = dmvt_vertices(tuple(terms))
    for i in range(r):
        for j in range(n_P):
            S_j = R + R.T - P[j]
            for rho in vertices:
                N_rho = N[i] + sum(value * term for value, term in zip(rho, error_terms, strict=True))
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
    error_terms: Sequence[FloatArray],
    terms: Sequence[DMVTTerm],
    points_per_axis: int = GRID_POINTS_PER_AXIS,
    rho_points: int = GRID_RHO_POINTS,
) -> tuple[float, dict[str, float], int]:
    """Max spectral radius of N(h) + sum_k rho_k M G_k c_k^T over the premise box x the box of rho.

    Parameters
    ----------
    nts : NTSModel
        The model whose premise box and memberships are gridded.
    N : (r, n, n) ndarray
        N_i, physical coordinates.
    error_terms : sequence of (n, n) ndarray
        M G_k c_k^T per DMVT term.
    terms : sequence of DMVTTerm
        The DMVT terms (their bounds).
    points_per_axis : int
        Grid points per premise axis.
    rho_points : int
        Points per rho with one DMVT term; 3 (both ends and the centre) per rho with several.

    Returns
    -------
    radius : float
        The largest spectral radius on the grid.
    where : dict of str to float
        Where it occurs: speed_mps, yaw_rate_radps, rho and the other terms' names.
    points : int
        The number of points checked.
    """
    V = np.linspace(nts.premise_low[0], nts.premise_high[0], points_per_axis)
    r = np.linspace(nts.premise_low[1], nts.premise_high[1], points_per_axis)
    per_rho = rho_points if len(terms) == 1 else 3
    rho_axes = [np.linspace(t.low, t.high, per_rho) for t in terms]
    grid = np.meshgrid(V, r, *rho_axes, indexing="ij")
    VV, rr, rhos = grid[0].ravel(), grid[1].ravel(), [g.ravel() for g in grid[2:]]
    h = nts.memberships(np.stack([VV, rr], axis=-1))
    stack = np.einsum("gi,ijk->gjk", h, N)
    for rho, matrix in zip(rhos, error_terms, strict=True):
        stack = stack + rho[:, None, None] * matrix
    radii = np.abs(np.linalg.eigvals(stack)).max(axis=-1)
    worst = int(np.argmax(radii))
    where = {"speed_mps": float(1.0 / VV[worst]), "yaw_rate_radps": float(rr[worst])}
    for k, (rho, term) in enumerate(zip(rhos, terms, strict=True)):
        where["rho" if k == 0 else term.name] = float(rho[worst])
    return float(radii[worst]), where, int(radii.size)


def verify(
    nts: NTSModel,
    terms: Sequence[DMVTTerm],
    P: FloatArray,
    R: FloatArray,
    alpha: float,
    N_physical: FloatArray,
    M_physical: FloatArray,
    T: FloatArray,
    *,
    spectral_radius: tuple[float, dict[str, float], int] | None = None,
) -> VerificationReport:
    """Run checks 1-3 on gains in physical coordinates.

    The LMIs are checked in the design coordinates x' = T x_bar (well conditioned), the spectral radius on the
    runtime gains in physical coordinates.

    Parameters
    ----------
    nts : NTSModel
        The model (premise box, memberships).
    terms : sequence of DMVTTerm
        The DMVT terms of the augmented model (physical coordinates).
    P, R : ndarray
        The Lyapunov matrices (r or 1, n, n) and the slack matrix (n, n), design coordinates.
    alpha : float
        The decay rate per sample the LMIs were posed at.
    N_physical, M_physical : ndarray
        The runtime N_i (r, n, n) and M (n, n).
    T : (n, n) ndarray
        The change to design coordinates.
    spectral_radius : (float, dict, int), optional
        Check 3's grid result (radius, where, points) for these N_physical and M_physical on this model, when
        it was already computed (a switched design's fast set, verified on its own before); it is then not
        recomputed, and is still compared with the decay rate certified here.

    Returns
    -------
    VerificationReport
        Every figure the certificate records.

    Raises
    ------
    VerificationFailed
        A check fails; the message names the first that does.
    """
    T_inv = np.linalg.inv(T)
    N_design = np.einsum("ab,ibc,cd->iad", T, N_physical, T_inv)
    design_terms = [term.transformed(T, T_inv) for term in terms]
    M_design = T @ M_physical @ T_inv
    lmi_min, P_min, slack_min, certified = verify_lyapunov(
        N_design, error_term_matrices(design_terms, M_design), design_terms, P, R, alpha
    )
    if spectral_radius is None:
        spectral_radius = spectral_radius_grid(nts, N_physical, error_term_matrices(terms, M_physical), terms)
    radius, where, points = spectral_radius
    report = VerificationReport(
        lmi_min_eigenvalues=lmi_min,
        P_min_eigenvalues=P_min,
        slack_min_eigenvalue=slack_min,
        certified_decay_rate=certified,
        spectral_radius_max=radius,
        spectral_radius_at=where,
        grid_points=points,
    )
    _raise_on_failure(report, max(1.0, float(np.abs(P).max()), float(np.abs(R).max())), alpha)
    return report


def _raise_on_failure(report: VerificationReport, scale: float, alpha: float) -> None:
    """Raise :class:`VerificationFailed` naming the first of checks 1-3 that ``report`` fails; ``scale``: the
    size of P and R the strictness threshold is relative to."""
    details: dict[str, object] = {"report": asdict(report)}
    P_min, lmi_min, certified = report.P_min_eigenvalues, report.lmi_min_eigenvalues, report.certified_decay_rate
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
    radius, where = report.spectral_radius_max, report.spectral_radius_at
    if radius >= 1.0 or radius > certified + 1e-7:
        raise VerificationFailed(
            f"spectral radius {radius:.6f} of the error dynamics at v_x = {where['speed_mps']:.2f} m/s, "
            f"r = {where['yaw_rate_radps']:.3f} rad/s, rho = {where.get('rho', 0.0):.2f} exceeds the certified "
            f"decay rate {certified:.6f}",
            details,
        )


def merged(first: VerificationReport, second: VerificationReport) -> VerificationReport:
    """One report for two gain sets verified with the same P(h) and R.

    Parameters
    ----------
    first, second : VerificationReport
        The two sets' reports.

    Returns
    -------
    VerificationReport
        The worse figure of each, both LMI lists.
    """
    worse = first if first.spectral_radius_max >= second.spectral_radius_max else second
    return VerificationReport(
        lmi_min_eigenvalues=first.lmi_min_eigenvalues + second.lmi_min_eigenvalues,
        P_min_eigenvalues=first.P_min_eigenvalues,
        slack_min_eigenvalue=min(first.slack_min_eigenvalue, second.slack_min_eigenvalue),
        certified_decay_rate=max(first.certified_decay_rate, second.certified_decay_rate),
        spectral_radius_max=worse.spectral_radius_max,
        spectral_radius_at=worse.spectral_radius_at,
        grid_points=first.grid_points + second.grid_points,
    )


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


def build_certificate(
    options: DesignOptions,
    report: VerificationReport,
    info: SolveInfo,
    *,
    lmi_form: str,
    alpha: float,
    n_lmis_solved: int,
    solves: int,
    timings: dict[str, float],
    gains_hash: str,
    symmetry: str,
    performance: dict[str, float] | None = None,
    notes: list[str] | None = None,
) -> Certificate:
    """The certificate of a verified design: the one place a :class:`Certificate` is made.

    Parameters
    ----------
    options : DesignOptions
        The design's options.
    report : VerificationReport
        What the numpy verification found.
    info : SolveInfo
        What the solver of the accepted point reported.
    lmi_form : str
        "vertex" or "petersen".
    alpha : float
        The decay rate per sample the LMIs were posed at.
    n_lmis_solved : int
        LMIs in the solved problem.
    solves : int
        Solver runs the design took.
    timings : dict of str to float
        Wall times of the design's stages [s].
    gains_hash : str
        The content hash of the runtime gains (synth.gains.gains_hash).
    symmetry : str
        "mirror" or "none".
    performance : dict of str to float, optional
        Guaranteed costs and other figures of the design.
    notes : list of str, optional
        What the figures mean.

    Returns
    -------
    Certificate
        The certificate.
    """
    return Certificate(
        design=options.design,
        fault_order=options.fault_order,
        lyapunov=options.lyapunov,
        lmi_form=lmi_form,
        decoupled=options.decoupled,
        verified=True,
        decay_rate=report.certified_decay_rate,
        requested_decay_rate=alpha,
        spectral_radius_max=report.spectral_radius_max,
        spectral_radius_at=report.spectral_radius_at,
        grid_points=report.grid_points,
        n_lmis_solved=n_lmis_solved,
        n_lmis_verified=len(report.lmi_min_eigenvalues),
        lmi_min_eigenvalue=min(report.lmi_min_eigenvalues),
        lmi_min_eigenvalues=report.lmi_min_eigenvalues,
        P_min_eigenvalues=report.P_min_eigenvalues,
        margin=options.margin,
        solver=info.solver,
        solver_version=solver_version(info.solver),
        solver_status=info.status,
        solver_iterations=info.iterations,
        solves=solves,
        timings_s={k: round(v, 6) for k, v in timings.items()},
        content_hash=gains_hash,
        symmetry=symmetry,
        performance=dict(performance or {}),
        notes=list(notes or []),
    )


def content_hash(arrays: dict[str, FloatArray], meta: dict[str, Any]) -> str:
    """SHA-256 of the gain arrays (float64, C order) and the canonical JSON of ``meta``.

    Parameters
    ----------
    arrays : dict of str to ndarray
        The arrays, hashed in the order of their names.
    meta : dict
        JSON-serialisable metadata.

    Returns
    -------
    str
        The hex digest.
    """
    digest = hashlib.sha256()
    digest.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(arrays):
        digest.update(name.encode())
        digest.update(np.ascontiguousarray(arrays[name], dtype="<f8").tobytes())
    return digest.hexdigest()

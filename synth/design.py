"""Observer synthesis: existence checks, LMI solve with solver fallback, verification, decay-rate bisection.

:func:`synthesize` is the one entry point: vehicle parameters, bounds and
options in, :class:`~synth.gains.ObserverGains` with a verified certificate
out, or an exception of :mod:`synth.errors` that says why not.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NoReturn

import numpy as np

from synth.augmented import AugmentedModel
from synth.certificate import VerificationReport, build_certificate, verify
from synth.errors import SolverFailed, VerificationFailed
from synth.existence import check_decoupled_detectability, check_detectability
from synth.fuzzy import NTSModel
from synth.gains import ObserverGains, gains_hash
from synth.lmi import DesignCoordinates, LMISolution, Theorem2LMIs, design_coordinates, gains_from_solution
from synth.model import FloatArray
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams
from synth.robust import synthesize_robust


@dataclass(frozen=True)
class _Verified:
    solution: LMISolution
    report: VerificationReport
    M: FloatArray
    N: FloatArray
    L: FloatArray


def synthesize(
    params: VehicleParams | None = None,
    bounds: OperatingBounds | None = None,
    options: DesignOptions | None = None,
    *,
    use_symmetry: bool = True,
) -> ObserverGains:
    """Design certified observer gains (Theorem 2, or the robust design). Never returns unverified gains.

    Parameters
    ----------
    params, bounds : VehicleParams, OperatingBounds, optional
        The vehicle and the operating box the certificate covers (the paper's, eq. (13), if None).
    options : DesignOptions, optional
        The design options (the product's default design if None).
    use_symmetry : bool, default True
        Pose the LMIs on mirror-invariant points when the data have the left-right symmetry (synth.symmetry;
        lossless). False only to measure what it saves.

    Returns
    -------
    ObserverGains
        Verified gains with their certificate.

    Raises
    ------
    Infeasible, SolverFailed, VerificationFailed
        The design cannot exist (with the reason), no solver returned a point, or no returned point passed the
        numpy check.
    """
    params = params or VehicleParams()
    bounds = bounds or OperatingBounds()
    options = options or DesignOptions()
    if options.design == "robust":
        return synthesize_robust(params, bounds, options, use_symmetry=use_symmetry)
    started = time.perf_counter()
    timings: dict[str, float] = {}
    aug = AugmentedModel.build(NTSModel.build(params, bounds), options.fault_order)
    if options.check_existence:
        if options.decoupled:
            check_decoupled_detectability(aug)
        else:
            check_detectability(aug)
    timings["existence_s"] = time.perf_counter() - started

    mark = time.perf_counter()
    dc = design_coordinates(
        aug, difference=options.difference_coordinates, torque_fault_scale=options.torque_fault_scale
    )
    lmis = Theorem2LMIs(
        dc,
        decoupled=options.decoupled,
        lyapunov=options.lyapunov,
        form=options.lmi_form,
        margin=options.margin,
        use_symmetry=use_symmetry,
    )
    timings["build_s"] = time.perf_counter() - mark

    mark = time.perf_counter()
    solves = 0
    best, failures = _solve_verified(lmis, aug, dc, 1.0, options.solvers, options.solver_time_limit_s)
    solves += len(options.solvers) if best is None else 1 + len(failures)
    if best is None:
        _raise_no_design(failures, lmis.n_lmis, options.solvers)
    timings["solve_s"] = time.perf_counter() - mark
    timings["compile_s"] = best.solution.info.compile_s
    timings["solver_s"] = best.solution.info.solver_s

    if options.optimise_decay_rate:
        mark = time.perf_counter()
        best, probes = _bisect_decay_rate(lmis, aug, dc, best, options)
        solves += probes
        timings["bisection_s"] = time.perf_counter() - mark

    timings["total_s"] = time.perf_counter() - started
    return _package(params, bounds, options, aug, dc, lmis, best, timings, solves)


def _raise_no_design(failures: list[Exception], n_lmis: int, solvers: Sequence[str]) -> NoReturn:
    """Raise why no solver gave verified gains: VerificationFailed when every solver's point failed the numpy
    check, else SolverFailed."""
    if failures and all(isinstance(f, VerificationFailed) for f in failures):
        raise VerificationFailed(
            "every solver returned gains that fail the numpy verification: " + "; ".join(str(f) for f in failures),
            {"failures": [str(f) for f in failures]},
        )
    raise SolverFailed(
        f"no solver found a feasible point of the {n_lmis} LMIs of Theorem 2 "
        f"({', '.join(solvers)}): " + "; ".join(str(f) for f in failures)
    )


def _solve_verified(
    lmis: Theorem2LMIs,
    aug: AugmentedModel,
    dc: DesignCoordinates,
    alpha: float,
    solvers: tuple[str, ...],
    time_limit_s: float,
) -> tuple[_Verified | None, list[Exception]]:
    """Try each solver in turn; return the first solution that passes verification."""
    failures: list[Exception] = []
    for solver in solvers:
        try:
            solution = lmis.solve(alpha, solver, time_limit_s)
        except SolverFailed as exc:
            failures.append(exc)
            continue
        try:
            return _check(aug, dc, solution), failures
        except VerificationFailed as exc:
            failures.append(VerificationFailed(f"{solver} ({solution.info.status}): {exc}", exc.details))
    return None, failures


def _check(aug: AugmentedModel, dc: DesignCoordinates, solution: LMISolution) -> _Verified:
    M, N, L = gains_from_solution(dc, solution.E, solution.H)
    N_phys = np.einsum("ab,ibc,cd->iad", dc.T_inv, N, dc.T)
    M_phys = dc.T_inv @ M @ dc.T
    report = verify(aug.nts, aug.dmvt_terms, solution.P, solution.R, solution.alpha, N_phys, M_phys, dc.T)
    return _Verified(solution=solution, report=report, M=M, N=N, L=L)


def _bisect_decay_rate(
    lmis: Theorem2LMIs,
    aug: AugmentedModel,
    dc: DesignCoordinates,
    feasible: _Verified,
    options: DesignOptions,
) -> tuple[_Verified, int]:
    """Bisection on alpha (N^T P N < alpha^2 P): the smallest certified decay rate.

    Only the first solver is used while probing: a probe that fails, for any
    reason, counts as infeasible, which can only make the result conservative.
    """
    best = feasible
    high = feasible.report.certified_decay_rate
    # Every frozen error matrix of a design with decay rate alpha has spectral
    # radius below alpha. The first design's worst radius is where the physics
    # floor usually lies (NOTES.md, finding 4), so probe there first; if it is
    # feasible after all, fall back to plain bisection below it.
    low = min(feasible.report.spectral_radius_max, high)
    probes = 0
    candidate, _ = _solve_verified(lmis, aug, dc, low, options.solvers[:1], options.solver_time_limit_s)
    probes += 1
    if candidate is not None:
        best, high, low = candidate, min(low, candidate.report.certified_decay_rate), 0.0
    while high - low > options.decay_rate_tolerance and probes < 40:
        mid = 0.5 * (low + high)
        candidate, _ = _solve_verified(lmis, aug, dc, mid, options.solvers[:1], options.solver_time_limit_s)
        probes += 1
        if candidate is None:
            low = mid
        else:
            best = candidate
            high = min(mid, candidate.report.certified_decay_rate)
    return best, probes


def _package(
    params: VehicleParams,
    bounds: OperatingBounds,
    options: DesignOptions,
    aug: AugmentedModel,
    dc: DesignCoordinates,
    lmis: Theorem2LMIs,
    best: _Verified,
    timings: dict[str, float],
    solves: int,
) -> ObserverGains:
    """Back to physical coordinates, with the certificate."""
    T, T_inv = dc.T, dc.T_inv
    sol = best.solution
    N = np.einsum("ab,ibc,cd->iad", T_inv, best.N, T)
    L = np.einsum("ab,ibc->iac", T_inv, best.L)
    M = T_inv @ best.M @ T
    E = T_inv @ sol.E
    certificate = build_certificate(
        options,
        best.report,
        sol.info,
        lmi_form=options.lmi_form,
        alpha=sol.alpha,
        n_lmis_solved=lmis.n_lmis,
        solves=solves,
        timings=timings,
        gains_hash=gains_hash(params, bounds, options, N, L, M, E),
        symmetry="mirror" if lmis.symmetry is not None else "none",
    )
    return ObserverGains(
        params=params,
        bounds=bounds,
        options=options,
        N=N,
        L=L,
        M=M,
        E=E,
        P=sol.P,
        R=sol.R,
        T=T,
        certificate=certificate,
    )

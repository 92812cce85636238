"""The one module that talks to the conic solvers: their options, their versions, and a solve that raises.

Every design (Theorem 2 in :mod:`synth.lmi`, the noise-aware design in
:mod:`synth.robust`) poses a cvxpy problem and hands it to :func:`solve`,
which either returns what the solver reported (:class:`SolveInfo`) or raises
:class:`~synth.errors.SolverFailed` saying why. A returned point is never
trusted as it is: the caller re-verifies it in numpy (:mod:`synth.certificate`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING

from synth.errors import BadParameters, SolverFailed

if TYPE_CHECKING:  # cvxpy is imported where a problem is solved: the runtime (gains, observer) never needs it
    import cvxpy as cp

#: Solver settings: Clarabel on one thread with chordal decomposition (fastest
#: here), SCS at a tight tolerance as the fallback (its default tolerance
#: returned unstable "optimal" gains, NOTES.md finding 3).
SOLVER_OPTIONS: dict[str, dict[str, object]] = {
    "CLARABEL": {"max_threads": 1},
    "SCS": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 200_000},
}
#: The name of each solver's wall-clock limit option [s].
TIME_LIMIT_OPTION = {"CLARABEL": "time_limit", "SCS": "time_limit_secs"}
#: Statuses whose point is worth verifying (cvxpy's OPTIMAL and OPTIMAL_INACCURATE); anything else is a failure.
USABLE_STATUSES = ("optimal", "optimal_inaccurate")


@dataclass(frozen=True)
class SolveInfo:
    """What one solver call reported: the solver, its status and iterations, and where the time went [s]."""

    solver: str
    status: str
    iterations: int | None
    wall_s: float
    compile_s: float
    solver_s: float


def solver_version(solver: str) -> str:
    """The solver package's and cvxpy's versions, for the certificate.

    Parameters
    ----------
    solver : str
        A cvxpy solver name ("CLARABEL", "SCS").

    Returns
    -------
    str
        For example 'clarabel 0.9.0, cvxpy 1.5.2'.

    Raises
    ------
    BadParameters
        The solver's package is not installed.
    """
    package = {"CLARABEL": "clarabel", "SCS": "scs"}.get(solver, solver.lower())
    try:
        return f"{package} {metadata.version(package)}, cvxpy {metadata.version('cvxpy')}"
    except metadata.PackageNotFoundError as exc:
        raise BadParameters(f"solver {solver!r} is not installed") from exc


def solve(
    problem: cp.Problem,
    solver: str,
    time_limit_s: float,
    tolerances: dict[str, float] | None = None,
) -> SolveInfo:
    """Solve ``problem`` with ``solver`` within ``time_limit_s``.

    A status other than optimal or optimal_inaccurate is a failure.

    Parameters
    ----------
    problem : cvxpy.Problem
        The LMI problem.
    solver : str
        A solver of :data:`TIME_LIMIT_OPTION`.
    time_limit_s : float
        The solver's time limit [s].
    tolerances : dict, optional
        Overrides of the solver's defaults (for example a looser duality gap for an H2 objective that converges
        to 6-7 digits).

    Returns
    -------
    SolveInfo
        Solver, status, iterations and timings of the solve.

    Raises
    ------
    BadParameters
        The solver is unknown.
    SolverFailed
        The solver stopped without a usable point (the message gives its status or error).
    """
    import cvxpy as cp

    if solver not in TIME_LIMIT_OPTION:
        raise BadParameters(f"unknown solver {solver!r}; choose from {', '.join(TIME_LIMIT_OPTION)}")
    options = {**SOLVER_OPTIONS.get(solver, {}), **(tolerances or {}), TIME_LIMIT_OPTION[solver]: time_limit_s}
    started = time.perf_counter()
    try:
        # cvxpy warns "Solution may be inaccurate" on optimal_inaccurate: the status is kept in SolveInfo and
        # every point is verified in numpy afterwards, so the warning would only leak into the user's terminal
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Solution may be inaccurate", category=UserWarning)
            # what problem.solve does, with the explicit zeros of the constraint matrix dropped: a problem with
            # parameters (compiled once, synth.robust) keeps a zero wherever a parameter's value may be nonzero,
            # about half its entries for the H2 LMIs, and the solver's KKT factor would carry them all
            data, chain, inverse_data = problem.get_problem_data(solver, solver_opts=options)
            data[cp.settings.A].eliminate_zeros()
            solution = chain.solve_via_data(problem, data, True, False, options)
            problem.unpack_results(solution, chain, inverse_data)
    except cp.error.SolverError as exc:
        raise SolverFailed(f"{solver} stopped without a solution ({str(exc).split('.')[0]})") from exc
    wall_s = time.perf_counter() - started
    status = str(problem.status)
    if status not in USABLE_STATUSES:
        raise SolverFailed(f"{solver} status {status}")
    stats = problem.solver_stats
    return SolveInfo(
        solver=solver,
        status=status,
        iterations=stats.num_iters if stats is not None else None,
        wall_s=wall_s,
        compile_s=float(problem.compilation_time or 0.0),
        solver_s=float(stats.solve_time or 0.0) if stats is not None and stats.solve_time is not None else float("nan"),
    )


__all__ = ["SOLVER_OPTIONS", "TIME_LIMIT_OPTION", "SolveInfo", "solve", "solver_version"]

"""Existence conditions checked before any LMI is solved.

Exact disturbance decoupling (eq. 23, M D_bar = 0) with M = I + E C_bar needs
E C_bar D_bar = -D_bar, solvable iff rank(C_bar D_bar) = rank(D_bar)
(Lemma 2). Its general solution E = U + Y V (eqs. 37-39) turns the error
matrix of eq. (43) into

    N = M0 A_bar - [H, -Y] [C_bar; V C_bar A_bar],   M0 = I + U C_bar,

so a Schur-stable N exists at a frozen premise iff the pair
(M0 A_bar(xi), [C_bar; V C_bar A_bar(xi)]) is detectable. The polytopic LMIs
imply stability of every convex combination of the vertices, hence at every
point of the premise box: one undetectable point is enough to make the
design impossible. Without decoupling, the same test runs on (A_bar, C_bar).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.augmented import N_STATES, AugmentedModel
from synth.errors import Infeasible
from synth.model import FloatArray

#: Modes with |z| above this are treated as not asymptotically stable.
UNIT_CIRCLE_TOL = 1e-9
#: Relative singular-value threshold of the PBH rank test.
PBH_RANK_TOL = 1e-9


@dataclass(frozen=True)
class UndetectableMode:
    """An eigenvalue of the open-loop error matrix that no output injection moves."""

    eigenvalue: complex
    speed_mps: float
    yaw_rate_radps: float
    states: tuple[str, ...]
    eigenvector: FloatArray


def augmented_state_names(fault_order: int) -> list[str]:
    """Readable names of the augmented state, shift coordinates.

    Parameters
    ----------
    fault_order : int
        The fault model's order q.

    Returns
    -------
    list of str
        n = 3 + 2 q names: v_x, v_y, r, then the torque and steering faults of each shift.
    """
    names = ["longitudinal speed v_x", "lateral speed v_y", "yaw rate r"]
    for m in range(fault_order):
        suffix = "" if m == 0 else f" (shift {m})"
        names += [f"torque fault T_f{suffix}", f"steering fault delta_f{suffix}"]
    return names


def decoupling_matrices(aug: AugmentedModel) -> tuple[FloatArray, FloatArray]:
    """U = -D_bar (C_bar D_bar)^+ and V = I - (C_bar D_bar)(C_bar D_bar)^+ of eqs. (38)-(39).

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model (its C_bar and D_bar).

    Returns
    -------
    U : (n, p) ndarray
    V : (p, p) ndarray
    """
    CD = aug.C_bar @ aug.D_bar
    CD_pinv = np.linalg.pinv(CD)
    U = -aug.D_bar @ CD_pinv
    V = np.eye(CD.shape[0]) - CD @ CD_pinv
    return U, V


def check_decoupling_rank(aug: AugmentedModel) -> None:
    """Check that the wind can be decoupled: rank(C_bar D_bar) = rank(D_bar).

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model.

    Raises
    ------
    Infeasible
        The ranks differ (the message gives them).
    """
    rank_CD = np.linalg.matrix_rank(aug.C_bar @ aug.D_bar)
    rank_D = np.linalg.matrix_rank(aug.D_bar)
    if rank_CD != rank_D:
        raise Infeasible(
            "Exact wind decoupling is impossible: rank(C_bar D_bar) = "
            f"{rank_CD} differs from rank(D_bar) = {rank_D}, so no E satisfies "
            "E C_bar D_bar = -D_bar (eq. 36). The wind does not reach the measured "
            "outputs directly and cannot be cancelled by output injection.",
            {"rank_CD": int(rank_CD), "rank_D": int(rank_D)},
        )


def undetectable_modes(
    A: FloatArray, C_ext: FloatArray, names: list[str], speed_mps: float, yaw_rate_radps: float
) -> list[UndetectableMode]:
    """PBH test: the eigenvalues of A on or outside the unit circle that C_ext does not see.

    Parameters
    ----------
    A : (n, n) ndarray
        The error matrix at one premise.
    C_ext : (p, n) ndarray
        The output matrix (extended with what the design may use).
    names : list of str
        The state's names, for the modes' descriptions.
    speed_mps : float
        The premise's v_x [m/s].
    yaw_rate_radps : float
        The premise's r [rad/s].

    Returns
    -------
    list of UndetectableMode
        Empty when (A, C_ext) is detectable.
    """
    n = A.shape[0]
    eigenvalues, vectors = np.linalg.eig(A)
    modes = []
    for lam, _vec in zip(eigenvalues, vectors.T, strict=True):
        if abs(lam) < 1.0 - UNIT_CIRCLE_TOL:
            continue
        pencil = np.vstack([lam * np.eye(n) - A, C_ext])
        sv = np.linalg.svd(pencil, compute_uv=False)
        if sv[-1] > PBH_RANK_TOL * max(1.0, sv[0]):
            continue
        # the unobservable direction: right null vector of the pencil
        _, _, vh = np.linalg.svd(pencil)
        direction = np.abs(vh[-1].conj())
        direction = direction / direction.max()
        states = tuple(names[k] for k in np.flatnonzero(direction > 1e-6))
        modes.append(
            UndetectableMode(
                eigenvalue=complex(lam),
                speed_mps=speed_mps,
                yaw_rate_radps=yaw_rate_radps,
                states=states,
                eigenvector=np.real_if_close(vh[-1].conj()),
            )
        )
    return modes


def premise_grid(aug: AugmentedModel, points_per_axis: int) -> list[tuple[float, float, FloatArray]]:
    """A grid of the premise box, r = 0 and the box edges included.

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model (its premise box and memberships).
    points_per_axis : int
        Grid points per premise axis.

    Returns
    -------
    list of (float, float, ndarray)
        (v_x [m/s], r [rad/s], memberships (r_rules,)) at each point.
    """
    nts = aug.nts
    V_values = np.linspace(nts.premise_low[0], nts.premise_high[0], points_per_axis)
    r_values = np.union1d(np.linspace(nts.premise_low[1], nts.premise_high[1], points_per_axis), [0.0])
    r_values = r_values[(r_values >= nts.premise_low[1]) & (r_values <= nts.premise_high[1])]
    grid = []
    for V in V_values:
        for r in r_values:
            h = nts.memberships(np.array([V, r]))
            grid.append((float(1.0 / V), float(r), h))
    return grid


def check_decoupled_detectability(aug: AugmentedModel, points_per_axis: int = 9) -> None:
    """Check that the decoupled design (the paper's wind decoupling) can exist.

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model, whose wind input is to be decoupled.
    points_per_axis : int, default 9
        Grid points per premise axis where the decoupled error dynamics are tested.

    Raises
    ------
    Infeasible
        It cannot; the message is a readable paragraph saying why.
    """
    check_decoupling_rank(aug)
    U, V = decoupling_matrices(aug)
    M0 = np.eye(aug.n) + U @ aug.C_bar
    names = augmented_state_names(aug.fault_order)
    found: list[UndetectableMode] = []
    grid = premise_grid(aug, points_per_axis)
    for speed, yaw_rate, h in grid:
        A = aug.A_bar_at(h)
        C_ext = np.vstack([aug.C_bar, V @ aug.C_bar @ A])
        found += undetectable_modes(M0 @ A, C_ext, names, speed, yaw_rate)
    if not found:
        return
    first = min(found, key=lambda m: (abs(m.yaw_rate_radps), m.speed_mps))
    involved = " and the ".join(_collapse_chain(first.states))
    rates = sorted({round(m.yaw_rate_radps, 6) for m in found})
    bad_points = {(m.speed_mps, m.yaw_rate_radps) for m in found}
    everywhere = len(bad_points) == len(grid)
    extent = (
        f"the same holds at all {len(grid)} points of the premise grid"
        if everywhere
        else f"it is undetectable at {len(bad_points)} of {len(grid)} points of the premise grid"
    )
    raise Infeasible(
        "The paper's design with exact wind decoupling (M D_bar = 0, eq. 23) is "
        "impossible for this vehicle. The lateral wind enters only the yaw-rate "
        "equation, so cancelling it exactly uses up the yaw-rate measurement, and "
        "the longitudinal speed that is left cannot see every mode of the error "
        f"dynamics. At v_x = {first.speed_mps:.1f} m/s and r = {first.yaw_rate_radps:.2f} rad/s "
        f"the mode at z = {_format_complex(first.eigenvalue)}, which moves the {involved}, "
        "is unobservable, so no observer gain can make the estimation error "
        f"converge there ({extent}, yaw rates {rates[0]:.2f} to {rates[-1]:.2f} rad/s). "
        "The polytopic LMIs of Theorem 2 demand stability at every such point, so "
        "they are infeasible. Use the design without exact decoupling ('paper'), "
        "which treats the wind as a bounded disturbance, or the noise-aware "
        "'robust' design.",
        {
            "speed_mps": float(first.speed_mps),
            "yaw_rate_radps": float(first.yaw_rate_radps),
            "eigenvalue": [first.eigenvalue.real, first.eigenvalue.imag],
            "states": list(first.states),
            "undetectable_points": len(bad_points),
            "grid_points": len(grid),
        },
    )


def _collapse_chain(states: tuple[str, ...]) -> list[str]:
    """State names with each fault-model chain reduced to its fault, faults first."""
    names = list(dict.fromkeys(s.split(" (shift")[0] for s in states))
    return sorted(names, key=lambda s: ("fault" not in s, s))


def _format_complex(z: complex) -> str:
    return f"{z.real:.3f}" if abs(z.imag) < 1e-9 else f"{z.real:.3f}{z.imag:+.3f}j"


def check_detectability(aug: AugmentedModel, points_per_axis: int = 9) -> None:
    """Check that (A_bar(xi), C_bar) is detectable everywhere in the premise box.

    Parameters
    ----------
    aug : AugmentedModel
        The augmented model.
    points_per_axis : int, default 9
        Grid points per premise axis.

    Raises
    ------
    Infeasible
        Some premise has an undetectable mode (the message names it).
    """
    names = augmented_state_names(aug.fault_order)
    for speed, yaw_rate, h in premise_grid(aug, points_per_axis):
        modes = undetectable_modes(aug.A_bar_at(h), aug.C_bar, names, speed, yaw_rate)
        if modes:
            mode = modes[0]
            moved = " and the ".join(_collapse_chain(mode.states))
            raise Infeasible(
                f"The augmented model is not detectable from y = [v_x, r]: at v_x = "
                f"{speed:.1f} m/s and r = {yaw_rate:.2f} rad/s the mode at z = "
                f"{_format_complex(mode.eigenvalue)}, which moves the {moved}, "
                "is unobservable, so no observer gain can estimate it.",
                {"speed_mps": float(speed), "yaw_rate_radps": float(yaw_rate), "states": list(mode.states)},
            )


__all__ = [
    "N_STATES",
    "UndetectableMode",
    "augmented_state_names",
    "check_decoupled_detectability",
    "check_decoupling_rank",
    "check_detectability",
    "decoupling_matrices",
    "premise_grid",
]

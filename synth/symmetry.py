"""Lossless symmetry reduction of the observer LMIs: the vehicle's left-right mirror.

Turning left or right is the same physics with the signs of (v_y, r, delta_f)
flipped. In the augmented model of eq. (18) this is a signature matrix
S = diag(s), s = +1 on [v_x, T_f chain] and -1 on [v_y, r, delta_f chain],
with S_y = diag(+1, -1) on y = [v_x, r]:

    S A_bar_i S = A_bar_sigma(i),   S_y C_bar S = C_bar,   S G_bar e_vy^T S = G_bar e_vy^T,

where sigma swaps the rules at r_min and r_max. (The paper's DMVT term is
invariant because G_bar and e_vy^T flip sign together, whatever S_rho is. The
cornering drag's terms G_c e_vy^T and G_c e_deltaf^T are odd, S G S = -G, and
their rho intervals are centred on zero, so rho -> -rho maps each onto itself.)
It holds whenever the yaw-rate bounds are symmetric, r_min = -r_max, which is
the usual case and the paper's.

If (P_i, R, X_i, W, lambda_ij, Z) is feasible for the LMIs of Theorem 2 (or
of the robust design), so is its mirror image (S P_sigma(i) S, S R S,
S X_sigma(i) S_y, ...), because every LMI (i, j) of the image is a
congruence of LMI (sigma(i), sigma(j)) of the original. The feasible set is
convex and the objective invariant, so the average of the two is feasible
and as good: nothing is lost by searching only among mirror-invariant points
(Gatermann and Parrilo, "Symmetry groups, semidefinite programs, and sums of
squares", J. Pure Appl. Algebra 192, 2004). Among those, LMI (i, j) and LMI
(sigma(i), sigma(j)) are the same condition, so only one of each pair is
posed, and R, the P_i of self-mirrored rules, W and the other invariant
matrices split into an even and an odd block.

For the paper's 4 rules this halves the LMIs (16 -> 8 in the Petersen form,
32 -> 16 in the vertex form) and the free entries of P and R; Clarabel's
time per iteration falls by about 7x (docs/benchmarks/synthesis.md). The
numpy verification (synth.certificate) is unchanged: it checks every vertex
LMI of the full family on the reconstructed matrices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from synth.model import FloatArray

#: Relative tolerance of the invariance checks.
SYMMETRY_TOL = 1e-9


@dataclass(frozen=True)
class MirrorSymmetry:
    """A signature symmetry of the LMI data in the solver's coordinates.

    state_sign : (n,) +1 or -1 per design coordinate
    output_sign : (p,) +1 or -1 per measured output
    rule_map : sigma, an involution of the rule indices with S A_i S = A_sigma(i)
    """

    state_sign: FloatArray
    output_sign: FloatArray
    rule_map: tuple[int, ...]

    @property
    def S(self) -> FloatArray:
        return np.diag(self.state_sign)

    @property
    def S_y(self) -> FloatArray:
        return np.diag(self.output_sign)


def physical_mirror_sign(n: int) -> FloatArray:
    """The mirror's signature in physical shift coordinates [v_x, v_y, r, T_f, delta_f, ...].

    Parameters
    ----------
    n : int
        The augmented state's size.

    Returns
    -------
    (n,) ndarray
        +1 on v_x and the torque faults, -1 on v_y, r and the steering faults.
    """
    sign = np.ones(n)
    sign[1:3] = -1.0  # v_y, r
    sign[4::2] = -1.0  # every delta_f component of the fault chain
    return sign


def _close(a: FloatArray, b: FloatArray) -> bool:
    return bool(np.abs(a - b).max(initial=0.0) <= SYMMETRY_TOL * (1.0 + np.abs(b).max(initial=0.0)))


def find_mirror_symmetry(
    T: FloatArray,
    T_inv: FloatArray,
    A: FloatArray,
    C: FloatArray,
    dmvt_terms: Sequence[tuple[FloatArray, float]],
) -> MirrorSymmetry | None:
    """The mirror symmetry of the design data.

    None when the signature is not diagonal in these coordinates, when some S A_i S is not another vertex
    (asymmetric yaw-rate bounds), when C is not invariant, or when a DMVT term is neither invariant nor odd
    (S G c^T S = -G c^T) with its interval centred on zero (then rho -> -rho maps the interval onto itself).

    Parameters
    ----------
    T, T_inv : (n, n) ndarray
        The design coordinates x' = T x_bar and back.
    A : (r, n, n) ndarray
        The vertex matrices, design coordinates.
    C : (p, n) ndarray
        The output matrix, design coordinates.
    dmvt_terms : sequence of ((n, n) ndarray, float)
        Each DMVT term G_k c_k^T with the centre of its rho interval.

    Returns
    -------
    MirrorSymmetry or None
        The symmetry (signature, rule map), or None when the data do not have it.
    """
    n = A.shape[1]
    p = C.shape[0]
    if p != 2:
        return None
    S_design = T @ np.diag(physical_mirror_sign(n)) @ T_inv
    sign = np.diag(S_design).copy()
    if not _close(S_design, np.diag(sign)) or not _close(np.abs(sign), np.ones(n)):
        return None
    sign = np.sign(sign)
    S = np.diag(sign)
    S_y = np.diag([1.0, -1.0])
    if not _close(S_y @ C @ S, C):
        return None
    for term, centre in dmvt_terms:
        image = S @ term @ S
        if not (_close(image, term) or (centre == 0.0 and _close(image, -term))):
            return None
    rule_map = []
    for i in range(A.shape[0]):
        image = S @ A[i] @ S
        matches = [j for j in range(A.shape[0]) if _close(image, A[j])]
        if len(matches) != 1:
            return None
        rule_map.append(matches[0])
    if any(rule_map[rule_map[i]] != i for i in range(len(rule_map))):
        return None
    return MirrorSymmetry(state_sign=sign, output_sign=np.diag(S_y).copy(), rule_map=tuple(rule_map))


def columns_sign(B: FloatArray, state_sign: FloatArray) -> FloatArray | None:
    """The sign of each column of B under the mirror (S b = +-b).

    Parameters
    ----------
    B : (n, m) ndarray
        The columns.
    state_sign : (n,) ndarray
        The mirror's signature S.

    Returns
    -------
    (m,) ndarray or None
        +1 or -1 per column, or None if some column has no parity.
    """
    signs = []
    for col in B.T:
        if _close(state_sign * col, col):
            signs.append(1.0)
        elif _close(state_sign * col, -col):
            signs.append(-1.0)
        else:
            return None
    return np.array(signs)


class Parametrisation:
    """Decision variables of the observer LMIs, free or restricted to mirror-invariant points.

    Each method returns full-size cvxpy expressions, so the LMIs are written
    once for both cases; :meth:`pairs` says which rule pairs (i, j) to pose.
    """

    def __init__(self, symmetry: MirrorSymmetry | None) -> None:
        self.symmetry = symmetry

    # ---------------------------------------------------------------- helpers

    @staticmethod
    def _selector(sign: FloatArray, which: float) -> FloatArray:
        return np.eye(sign.size)[sign == which]

    def _invariant(self, rows: FloatArray, cols: FloatArray, name: str, symmetric: bool = False) -> cp.Expression:
        """A matrix M with diag(rows) M diag(cols) = M: free entries only where the signs agree."""
        parts: list[cp.Expression] = []
        for which in (1.0, -1.0):
            Sr, Sc = self._selector(rows, which), self._selector(cols, which)
            if Sr.shape[0] == 0 or Sc.shape[0] == 0:
                continue
            tag = "even" if which > 0 else "odd"
            if symmetric:
                block = cp.Variable((Sr.shape[0], Sr.shape[0]), symmetric=True, name=f"{name}_{tag}")
            else:
                block = cp.Variable((Sr.shape[0], Sc.shape[0]), name=f"{name}_{tag}")
            parts.append(Sr.T @ block @ Sc)
        if not parts:
            return cp.Constant(np.zeros((rows.size, cols.size)))
        total = parts[0]
        for part in parts[1:]:
            total = total + part
        return total

    # ------------------------------------------------------------- variables

    def square(self, n: int, name: str, *, symmetric: bool = False) -> cp.Expression:
        """An (n, n) matrix that the mirror leaves unchanged (R, or a common P)."""
        if self.symmetry is None:
            return cp.Variable((n, n), symmetric=symmetric, name=name)
        s = self.symmetry.state_sign
        return self._invariant(s, s, name, symmetric=symmetric)

    def per_rule_square(self, n: int, n_rules: int, name: str, *, symmetric: bool = False) -> list[cp.Expression]:
        """M_1..M_r with M_sigma(i) = S M_i S (the fuzzy Lyapunov matrices P_i)."""
        if self.symmetry is None:
            return [cp.Variable((n, n), symmetric=symmetric, name=f"{name}{i + 1}") for i in range(n_rules)]
        S, sigma = self.symmetry.S, self.symmetry.rule_map
        out: dict[int, cp.Expression] = {}
        for i in range(n_rules):
            if i in out:
                continue
            if sigma[i] == i:
                out[i] = self.square(n, f"{name}{i + 1}", symmetric=symmetric)
            else:
                out[i] = cp.Variable((n, n), symmetric=symmetric, name=f"{name}{i + 1}")
                out[sigma[i]] = S @ out[i] @ S
        return [out[i] for i in range(n_rules)]

    def per_rule_gain(self, n: int, p: int, n_rules: int, name: str) -> list[cp.Expression]:
        """X_1..X_r, (n, p) each, with X_sigma(i) = S X_i S_y (X_i = R H_i of eq. 40)."""
        if self.symmetry is None:
            return [cp.Variable((n, p), name=f"{name}{i + 1}") for i in range(n_rules)]
        S, S_y, sigma = self.symmetry.S, self.symmetry.S_y, self.symmetry.rule_map
        out: dict[int, cp.Expression] = {}
        for i in range(n_rules):
            if i in out:
                continue
            if sigma[i] == i:
                out[i] = self.gain(n, p, f"{name}{i + 1}")
            else:
                out[i] = cp.Variable((n, p), name=f"{name}{i + 1}")
                out[sigma[i]] = S @ out[i] @ S_y
        return [out[i] for i in range(n_rules)]

    def gain(self, n: int, p: int, name: str) -> cp.Expression:
        """An (n, p) matrix with S M S_y = M (W = R E, or a rule-independent gain)."""
        if self.symmetry is None:
            return cp.Variable((n, p), name=name)
        return self._invariant(self.symmetry.state_sign, self.symmetry.output_sign, name)

    def rectangular(self, rows_sign: FloatArray, cols_sign: FloatArray, name: str) -> cp.Expression:
        """A matrix with given row and column parities, free when there is no symmetry."""
        if self.symmetry is None:
            return cp.Variable((rows_sign.size, cols_sign.size), name=name)
        return self._invariant(rows_sign, cols_sign, name)

    def cost_matrix(self, input_sign: FloatArray | None, m: int, name: str) -> cp.Expression:
        """The symmetric (m, m) cost matrix Z of the H2 design, invariant under the input signature."""
        if self.symmetry is None or input_sign is None:
            return cp.Variable((m, m), symmetric=True, name=name)
        return self._invariant(input_sign, input_sign, name, symmetric=True)

    # ------------------------------------------------------------------ LMIs

    def representatives(self, n_rules: int) -> list[int]:
        """One rule of each mirror orbit {i, sigma(i)} (every rule without symmetry)."""
        if self.symmetry is None:
            return list(range(n_rules))
        sigma = self.symmetry.rule_map
        return [i for i in range(n_rules) if i <= sigma[i]]

    def pairs(self, n_rules: int, n_P: int) -> list[tuple[int, int]]:
        """Rule pairs (i, j) to pose: all of them, or one per mirror orbit {(i, j), (sigma i, sigma j)}."""
        every = [(i, j) for i in range(n_rules) for j in range(n_P)]
        if self.symmetry is None:
            return every
        sigma = self.symmetry.rule_map
        kept: list[tuple[int, int]] = []
        seen: set[tuple[int, int]] = set()
        for i, j in every:
            if (i, j) in seen:
                continue
            kept.append((i, j))
            image = (sigma[i], sigma[j] if n_P == n_rules else j)
            seen.update({(i, j), image})
        return kept


__all__ = [
    "MirrorSymmetry",
    "Parametrisation",
    "columns_sign",
    "find_mirror_symmetry",
    "physical_mirror_sign",
]

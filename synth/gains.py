"""Certified observer gains: the output of a synthesis and the input of the runtime observer.

Gains are stored in physical shift coordinates, the paper's form of eq. (19):

    z_{k+1} = N(h) z_k + L(h) y_k + M T1 (g(xi_k) + B u_k) + M G_bar phi(x_hat_k)
    x_hat_k = z_k - E y_k

and the output gain K of the robust design, which reports the fault
estimates filtered with the current measurement, x_hat_k + K (y_k - C_bar x_hat_k)
(zero for the paper's designs; see synth.robust).

A switched robust design (``DesignOptions.switching``) carries a second,
quiet gain set (N, L, K) beside the default one; both share M, E and the
Lyapunov multipliers P_i, R, so both are verified against the same P(h).

The Lyapunov multipliers P_i, R are kept in the solver's coordinates
(x' = T x_bar) where they are well conditioned, with T alongside, so that a
stored design can be re-verified anywhere.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np

from synth.augmented import N_FAULTS, N_OUTPUTS, N_STATES, AugmentedModel
from synth.certificate import Certificate, content_hash, error_term_matrices, verify
from synth.errors import VerificationFailed, check_shape
from synth.fuzzy import RULE_CORNERS, NTSModel
from synth.model import FloatArray
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams

GAINS_FORMAT = "agv-fe-gains/1"


def _hashed_options(options: DesignOptions) -> dict[str, Any]:
    """The options in the hash; ``robust_cost`` only when not 'joint' and ``switching`` only for a switched
    design, so one-set designs made before these options existed keep their hash."""
    data = options.model_dump(mode="json")
    if data.get("robust_cost") == "joint":
        del data["robust_cost"]
    if data.get("switching", ...) is None:
        del data["switching"]
    return data


@dataclass(frozen=True)
class GainSet:
    """The quiet gain set of a switched design, physical coordinates: N (r, n, n), L (r, n, 2), K (n, 2)."""

    N: FloatArray
    L: FloatArray
    K: FloatArray


def gains_hash(
    params: VehicleParams,
    bounds: OperatingBounds,
    options: DesignOptions,
    N: FloatArray,
    L: FloatArray,
    M: FloatArray,
    E: FloatArray,
    K: FloatArray | None = None,
    quiet: GainSet | None = None,
) -> str:
    """Content hash of runtime gains and everything they were designed for.

    A zero (or absent) output gain K is left out, so gains designed before K existed keep their hash; so is an
    absent quiet set.

    Parameters
    ----------
    params : VehicleParams
        The vehicle.
    bounds : OperatingBounds
        The operating box.
    options : DesignOptions
        The design options.
    N, L, M, E : ndarray
        The runtime gains of eq. (19), physical coordinates: N (r, n, n), L (r, n, p), M (n, n), E (n, p).
    K : (n, p) ndarray, optional
        The output gain.
    quiet : GainSet, optional
        A switched design's quiet set.

    Returns
    -------
    str
        The SHA-256 hex digest (synth.certificate.content_hash).
    """
    meta = {
        "format": GAINS_FORMAT,
        "params": params.hashed(),
        "bounds": bounds.hashed(),
        "options": _hashed_options(options),
    }
    arrays = {"N": N, "L": L, "M": M, "E": E}
    if K is not None and np.any(K):
        arrays["K"] = K
    if quiet is not None:
        arrays.update({"N_quiet": quiet.N, "L_quiet": quiet.L, "K_quiet": quiet.K})
    return content_hash(arrays, meta)


@dataclass(frozen=True)
class ObserverGains:
    """Gains of eq. (19) with their certificate.

    N : (r, n, n); L : (r, n, 2); M : (n, n); E : (n, 2)   physical coordinates
    K : (n, 2) output gain (None: zero)                     physical coordinates
    quiet : the quiet set of a switched design (None: one set)  physical coordinates
    P : (r or 1, n, n); R : (n, n)                          design coordinates, shared by both sets
    T : (n, n)                                              x_design = T x_bar
    """

    params: VehicleParams
    bounds: OperatingBounds
    options: DesignOptions
    N: FloatArray
    L: FloatArray
    M: FloatArray
    E: FloatArray
    P: FloatArray
    R: FloatArray
    T: FloatArray
    certificate: Certificate
    K: FloatArray | None = None
    quiet: GainSet | None = None

    @property
    def switched(self) -> bool:
        """True for a switched design: a fast set (N, L, K) and a quiet set sharing P(h)."""
        return self.quiet is not None

    def quiet_gains(self) -> ObserverGains:
        """The quiet set as gains of its own (same model, P, R and certificate), for the runtime and analysis."""
        if self.quiet is None:
            raise ValueError("these gains have no quiet set (not a switched design)")
        return replace(self, N=self.quiet.N, L=self.quiet.L, K=self.quiet.K, quiet=None)

    @property
    def output_gain(self) -> FloatArray:
        """K, (n, 2): the reported estimate is x_hat_k + K (y_k - C_bar x_hat_k); zeros when there is none."""
        return np.zeros_like(self.E) if self.K is None else self.K

    @cached_property
    def model(self) -> AugmentedModel:
        """The augmented model the gains were designed for."""
        return AugmentedModel.build(NTSModel.build(self.params, self.bounds), self.options.fault_order)

    @property
    def version(self) -> str:
        """A short, stable identifier of these gains: the first 12 hex digits of the content hash."""
        return self.certificate.content_hash[:12]

    def content_hash(self) -> str:
        """Recompute the content hash of these gains (see :func:`gains_hash`)."""
        return gains_hash(self.params, self.bounds, self.options, self.N, self.L, self.M, self.E, self.K, self.quiet)

    def to_dict(self, *, matrices: bool = True) -> dict[str, Any]:
        """A JSON-ready dict of the gains, their design and certificate.

        Parameters
        ----------
        matrices : bool, default True
            Include the arrays; False gives a summary only.

        Returns
        -------
        dict
            What :meth:`from_dict` reads back.
        """
        data: dict[str, Any] = {
            "format": GAINS_FORMAT,
            "version": self.version,
            "params": self.params.model_dump(),
            "bounds": self.bounds.model_dump(),
            "options": self.options.model_dump(mode="json"),
            "certificate": asdict(self.certificate),
        }
        if matrices:
            data["matrices"] = {
                name: np.asarray(getattr(self, name)).tolist() for name in ("N", "L", "M", "E", "P", "R", "T")
            }
            if self.K is not None:
                data["matrices"]["K"] = np.asarray(self.K).tolist()
            if self.quiet is not None:
                for name in ("N", "L", "K"):
                    data["matrices"][f"{name}_quiet"] = np.asarray(getattr(self.quiet, name)).tolist()
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, reverify: bool = True) -> ObserverGains:
        """Rebuild gains from :meth:`to_dict` output; check the hash and, by default, re-run verification.

        Parameters
        ----------
        data : dict
            A gains document.
        reverify : bool, default True
            Re-run the numpy verification of the certificate.

        Returns
        -------
        ObserverGains
            The gains.

        Raises
        ------
        VerificationFailed
            The document is not one (format, a missing matrix, a matrix whose shape its fault order does not give or
            with non-finite entries: the message names it), its hash does not match its content, or the gains fail
            the verification.
        """
        if data.get("format") != GAINS_FORMAT:
            raise VerificationFailed(f"unknown gains format {data.get('format')!r}, expected {GAINS_FORMAT!r}")
        if "matrices" not in data:
            raise VerificationFailed("the gains document has no 'matrices' section")
        mats = {k: np.asarray(v, dtype=float) for k, v in data["matrices"].items()}
        missing = [name for name in ("N", "L", "M", "E", "P", "R", "T") if name not in mats]
        if missing:
            raise VerificationFailed(f"the gains document has no {', '.join(missing)} matrix")
        options = DesignOptions.model_validate(data["options"])
        _check_gain_shapes(mats, options.fault_order)
        gains = cls(
            params=VehicleParams.model_validate(data["params"]),
            bounds=OperatingBounds.model_validate(data["bounds"]),
            options=options,
            N=mats["N"],
            L=mats["L"],
            M=mats["M"],
            E=mats["E"],
            P=mats["P"],
            R=mats["R"],
            T=mats["T"],
            certificate=Certificate(**data["certificate"]),
            K=mats.get("K"),
            quiet=_quiet_from(mats),
        )
        if (gains.quiet is None) != (gains.options.switching is None):
            raise VerificationFailed(
                "a switched design needs both the switching rule in its options and the quiet gain set; "
                f"this document has {'no' if gains.options.switching is None else 'a'} rule and "
                f"{'no' if gains.quiet is None else 'a'} quiet set"
            )
        recomputed = gains.content_hash()
        if recomputed != gains.certificate.content_hash:
            raise VerificationFailed(
                f"content hash mismatch: the file says {gains.certificate.content_hash[:12]}, "
                f"the matrices hash to {recomputed[:12]}; the gains were altered or truncated"
            )
        if reverify:
            gains.reverify()
        return gains

    def error_terms(self) -> list[FloatArray]:
        """M G_k c_k^T of every DMVT term (synth.augmented.AugmentedModel.dmvt_terms), physical coordinates:
        the error dynamics are e_{k+1} = (N(h) + sum_k rho_k M G_k c_k^T) e_k (eqs. 27-28)."""
        return error_term_matrices(self.model.dmvt_terms, self.M)

    def design_frame(self) -> tuple[FloatArray, list[FloatArray]]:
        """N_i and the DMVT error terms, both in the design coordinates x' = T x_bar of P and R."""
        T, T_inv = self.T, np.linalg.inv(self.T)
        N_design = np.einsum("ab,ibc,cd->iad", T, self.N, T_inv)
        return N_design, [T @ term @ T_inv for term in self.error_terms()]

    def reverify(self) -> None:
        """Re-run the numpy verification of the stored design (both sets of a switched one); raise if it fails."""
        if self.quiet is not None:
            self.quiet_gains().reverify()
        verify(
            self.model.nts,
            self.model.dmvt_terms,
            self.P,
            self.R,
            self.certificate.requested_decay_rate,
            self.N,
            self.M,
            self.T,
        )


def _check_gain_shapes(mats: dict[str, FloatArray], fault_order: int) -> None:
    """Every matrix of a gains document has the shape its design needs; the first that has not is named."""
    n = N_STATES + N_FAULTS * fault_order
    r = len(RULE_CORNERS)
    expected = {
        "N": (r, n, n),
        "L": (r, n, N_OUTPUTS),
        "M": (n, n),
        "E": (n, N_OUTPUTS),
        "R": (n, n),
        "T": (n, n),
        "K": (n, N_OUTPUTS),
        "N_quiet": (r, n, n),
        "L_quiet": (r, n, N_OUTPUTS),
        "K_quiet": (n, N_OUTPUTS),
    }
    for name, shape in expected.items():
        if name in mats:
            check_shape(mats[name], shape, name, VerificationFailed)
    P = mats["P"]
    if P.ndim != 3 or P.shape[0] not in (1, r) or P.shape[1:] != (n, n):
        raise VerificationFailed(
            f"Incompatible dimensions of P matrix; expected (1, {n}, {n}) or ({r}, {n}, {n}) but found {P.shape}"
        )
    for name, value in mats.items():
        if not np.all(np.isfinite(value)):
            raise VerificationFailed(f"the {name} matrix of the gains document has non-finite entries")


def _quiet_from(mats: dict[str, FloatArray]) -> GainSet | None:
    names = ("N_quiet", "L_quiet", "K_quiet")
    present = [k for k in names if k in mats]
    if not present:
        return None
    if len(present) != len(names):
        raise VerificationFailed(f"the gains document has {present} but a quiet set needs all of {list(names)}")
    return GainSet(N=mats["N_quiet"], L=mats["L_quiet"], K=mats["K_quiet"])

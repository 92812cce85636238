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

from synth.augmented import AugmentedModel
from synth.certificate import Certificate, content_hash, verify
from synth.errors import VerificationFailed
from synth.fuzzy import NTSModel
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

    A zero (or absent) output gain K is left out, so gains designed before K existed keep their hash;
    so is an absent quiet set.
    """
    meta = {
        "format": GAINS_FORMAT,
        "params": params.model_dump(),
        "bounds": bounds.model_dump(),
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
        """A JSON-ready dict; ``matrices=False`` leaves out the arrays (summary only)."""
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
        """Rebuild gains from :meth:`to_dict` output; check the hash and, by default, re-run verification."""
        if data.get("format") != GAINS_FORMAT:
            raise VerificationFailed(f"unknown gains format {data.get('format')!r}, expected {GAINS_FORMAT!r}")
        if "matrices" not in data:
            raise VerificationFailed("the gains document has no 'matrices' section")
        mats = {k: np.asarray(v, dtype=float) for k, v in data["matrices"].items()}
        gains = cls(
            params=VehicleParams.model_validate(data["params"]),
            bounds=OperatingBounds.model_validate(data["bounds"]),
            options=DesignOptions.model_validate(data["options"]),
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

    def design_frame(self) -> tuple[FloatArray, FloatArray]:
        """N_i and the rank-one DMVT term M G_bar rho_row, both in design coordinates."""
        T, T_inv = self.T, np.linalg.inv(self.T)
        N_design = np.einsum("ab,ibc,cd->iad", T, self.N, T_inv)
        return N_design, T @ self.MG_row @ T_inv

    @property
    def MG_row(self) -> FloatArray:
        """M G_bar e_vy^T, physical coordinates: the error term per unit rho, (n, n)."""
        aug = self.model
        row = np.zeros((1, aug.n))
        row[0, 1] = 1.0
        return self.M @ aug.G_bar @ row

    def reverify(self) -> None:
        """Re-run the numpy verification of the stored design (both sets of a switched one); raise if it fails."""
        if self.quiet is not None:
            self.quiet_gains().reverify()
        N_design, MG_design = self.design_frame()
        verify(
            self.model.nts,
            N_design,
            MG_design,
            self.P,
            self.R,
            self.model.rho_vertices(),
            self.certificate.requested_decay_rate,
            self.N,
            self.MG_row,
        )


def _quiet_from(mats: dict[str, FloatArray]) -> GainSet | None:
    names = ("N_quiet", "L_quiet", "K_quiet")
    present = [k for k in names if k in mats]
    if not present:
        return None
    if len(present) != len(names):
        raise VerificationFailed(f"the gains document has {present} but a quiet set needs all of {list(names)}")
    return GainSet(N=mats["N_quiet"], L=mats["L_quiet"], K=mats["K_quiet"])

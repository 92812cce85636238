"""The exception tree of the synthesis package.

Every error names the offending matrix, parameter or operating point and the
value, so that a caller (CLI, REST API) can show it to a user unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class SynthesisError(Exception):
    """Base class: anything that prevents certified observer gains."""


class BadParameters(SynthesisError, ValueError):
    """Vehicle parameters, bounds or design options are inconsistent."""


class Infeasible(SynthesisError):
    """No gains of the requested structure exist, or the solver found none.

    ``reason`` is one readable paragraph; ``details`` carries the figures
    behind it (operating point, eigenvalue, offending states) for programs.
    """

    def __init__(self, reason: str, details: dict[str, object] | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.details = dict(details or {})


class SolverFailed(SynthesisError):
    """Every solver in the fallback chain failed to return a usable point."""


class VerificationFailed(SynthesisError):
    """A solver returned gains that the independent numpy check rejects."""

    def __init__(self, reason: str, details: dict[str, object] | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.details = dict(details or {})


class ShapeError(BadParameters):
    """An array entering synth from outside (stored gains, a batch of vehicles) has the wrong dimensions."""


def check_shape(
    value: Any, shape: tuple[int | None, ...], name: str, error: type[Exception] = ShapeError
) -> np.ndarray:
    """``value`` as an array of ``shape``, else ``error`` naming the matrix.

    In python-control's words: "Incompatible dimensions of N matrix; expected (4, 5, 5) but found (4, 5)".

    Parameters
    ----------
    value : array_like
        The array to check.
    shape : tuple of int or None
        The expected shape; None accepts any length on that axis.
    name : str
        The matrix's name in the message.
    error : type of Exception, default ShapeError
        The exception to raise.

    Returns
    -------
    ndarray
        ``value`` as an array.

    Raises
    ------
    ShapeError
        (or ``error``) when the shape differs.
    """
    array = np.asarray(value)
    if array.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(array.shape, shape, strict=True)
    ):
        shown = tuple("n" if want is None else want for want in shape)
        raise error(f"Incompatible dimensions of {name} matrix; expected {shown} but found {array.shape}")
    return array

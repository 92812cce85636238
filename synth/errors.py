"""The exception tree of the synthesis package.

Every error names the offending matrix, parameter or operating point and the
value, so that a caller (CLI, REST API) can show it to a user unchanged.
"""

from __future__ import annotations


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

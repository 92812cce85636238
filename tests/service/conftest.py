"""Fixtures of the service tests: fast certified gains, shared across the session."""

from __future__ import annotations

import pytest

from synth.design import synthesize
from synth.gains import ObserverGains
from synth.options import DesignOptions
from tests.service.helpers import FAST_DESIGN


@pytest.fixture(scope="session")
def fast_gains() -> ObserverGains:
    """Certified gains that solve in well under a second (fault order 1, common P, no bisection)."""
    return synthesize(options=DesignOptions(**FAST_DESIGN))

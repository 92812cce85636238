"""Shared by the whole suite: designs, each synthesised once per session, and a real PostgreSQL server."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator

import pytest

from agv_fe.pg_cluster import PostgresServer
from synth.design import synthesize
from synth.gains import ObserverGains
from synth.options import DesignOptions


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test a node id of its own: pytest-xdist's ``--dist loadfile`` (``make test``) keys its work by node id,
    so of tests sharing one all but the first would pass without having run. A shared id is an error instead."""
    counts = Counter(item.nodeid for item in items)
    shared = sorted(nodeid for nodeid, n in counts.items() if n > 1)
    if shared:
        raise pytest.UsageError(f"tests share a node id, so a parallel run would skip all but one: {shared[:5]}")


@pytest.fixture(scope="session")
def paper_gains() -> ObserverGains:
    """The paper's design (Theorem 2 without decoupling, fuzzy P, fault order 3) with decay-rate bisection."""
    return synthesize(options=DesignOptions(design="paper"))


@pytest.fixture(scope="session")
def paper_gains_order1() -> ObserverGains:
    """A fast design for tests that only need some certified gains."""
    return synthesize(options=DesignOptions(design="paper", fault_order=1, optimise_decay_rate=False))


@pytest.fixture(scope="session")
def robust_gains_default() -> ObserverGains:
    """The product's default design (robust H2, fault order 1, with the filtered fault output)."""
    return synthesize(options=DesignOptions())


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A real PostgreSQL server (Debian's binaries, a temporary cluster), started once per session when needed."""
    server = PostgresServer()
    try:
        server.init()
        yield server
    finally:
        server.close()


@pytest.fixture
def postgres_url(postgres_server: PostgresServer) -> str:
    """A fresh, empty database on the session's PostgreSQL server."""
    return postgres_server.database()

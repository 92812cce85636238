"""The suite's own rules (tests/conftest.py)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from tests.conftest import pytest_collection_modifyitems


@dataclass
class _Item:
    nodeid: str


def test_tests_sharing_a_node_id_stop_the_collection() -> None:
    shared = [_Item("tests/a.py::test_x"), _Item("tests/a.py::test_x"), _Item("tests/a.py::test_y")]
    with pytest.raises(pytest.UsageError, match=r"share a node id.*\['tests/a.py::test_x'\]"):
        pytest_collection_modifyitems(shared)  # type: ignore[arg-type]
    pytest_collection_modifyitems([_Item("tests/a.py::test_x[1]"), _Item("tests/a.py::test_x[2]")])  # type: ignore[arg-type]

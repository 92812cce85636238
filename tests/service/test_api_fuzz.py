"""Every REST operation under generated requests (schemathesis, bounded): no 5xx, and every answer matches the
OpenAPI document (schema and status codes), with and without the token, profile changes included."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.schemas import APIOperation
from schemathesis.specs.openapi.checks import response_schema_conformance, status_code_conformance

from tests.service.helpers import FAST_DESIGN, make_settings, running

#: Generated requests per operation: bounded so that the suite stays quick (CI runs it on every push).
EXAMPLES = 30
#: How long one generated request may take before the client gives up [s].
CLIENT_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    settings_ = make_settings(tmp_path_factory.mktemp("fuzz"), {"default": {"design": FAST_DESIGN}})
    with running(settings_) as srv:
        yield srv


def _openapi() -> dict[str, Any]:
    """The service's OpenAPI document, from the app itself (nothing is started): the operations to generate for."""
    import tempfile

    from service.main import create_app

    with tempfile.TemporaryDirectory() as directory:
        return dict(create_app(make_settings(Path(directory))).openapi())


#: The dashboard's event stream never ends by design (server-sent events): its own tests cover it (tests/web).
schema = schemathesis.openapi.from_dict(_openapi()).exclude(path="/ui/stream")
#: One test per operation, parametrized by pytest itself: each gets a node id of its own (``[GET /health]``), which
#: pytest-xdist's ``--dist loadfile`` (``make test``) needs; schemathesis's ``parametrize`` gives all one id.
OPERATIONS = [result.ok() for result in schema.get_all_operations()]
CHECKS = [not_a_server_error, response_schema_conformance, status_code_conformance]


@pytest.mark.parametrize("operation", OPERATIONS, ids=[operation.label for operation in OPERATIONS])
def test_no_operation_answers_5xx_or_outside_its_schema(operation: APIOperation, live: Any) -> None:
    @given(case=operation.as_strategy())
    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        suppress_health_check=list(HealthCheck),
        derandomize=True,  # the same requests every run: a failure is reproducible, CI time is bounded
    )
    def calls(case: Any) -> None:
        # a generous client timeout: a calibration request starts the worker process, slow on a busy machine
        case.call_and_validate(base_url=live.url, headers=live.auth, checks=CHECKS, timeout=CLIENT_TIMEOUT_S)
        # without the token: 401 where it is needed, still as documented
        case.call_and_validate(base_url=live.url, checks=CHECKS, timeout=CLIENT_TIMEOUT_S)

    calls()


def test_every_operation_of_the_service_is_fuzzed() -> None:
    """The parametrization above covers what the service documents (but the event stream), not a fixed list."""
    documented = {
        f"{method.upper()} {path}"
        for path, methods in _openapi()["paths"].items()
        for method in methods
        if path != "/ui/stream"
    }
    assert {operation.label for operation in OPERATIONS} == documented and len(documented) >= 20

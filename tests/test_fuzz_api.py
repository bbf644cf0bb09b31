"""Property-based fuzzing of every REST route (issue 14): schemathesis generates requests from the
console's own ``/openapi.json`` and sends them over HTTP to a real uvicorn server, once with the
token and once without. No request may get a 500; documented behaviour is checked too (status
codes and response bodies as the schema declares them, content types).

Bounded for CI: a few examples per route (``MAX_EXAMPLES``), no deadline per example (the machine is
shared); the whole module stays near a minute. The server's ``min_free_mb`` is set beyond any disk,
so a campaign the fuzzer manages to describe validly is refused with a 507 instead of spawning a
twin; the live SSE stream is left out (it never ends, the live tests cover it).
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from server_harness import AUTH, running_server

MAX_EXAMPLES = 6
# A real server on a shared machine is slow to answer and many generated requests are refused early.
SLOW_SERVER = [HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large,
               HealthCheck.large_base_example]


@schemathesis.serializer("application/toml")
def _toml_body(ctx, value) -> bytes:
    """Parameter uploads are TOML text (schema: a string): send the generated text as it is."""
    return value.encode("utf-8", "surrogatepass") if isinstance(value, str) else bytes(str(value), "utf-8")


@schemathesis.deserializer("application/toml")
def _toml_response(ctx, response) -> str:
    return response.content.decode("utf-8", "replace")


@schemathesis.check
def no_server_fault(ctx, response, case) -> None:
    """No 5xx but the documented 507 (the archive cannot be written) and 503 (a peer the route needs,
    the controller service, is not on the bus): both here by construction, as the fuzzed console runs
    without a stack; status_code_conformance checks that the route documents them."""
    if response.status_code >= 500 and response.status_code not in (503, 507):
        raise AssertionError(f"{response.status_code} for {case.method} {case.formatted_path}: "
                             f"{response.text[:300]}")


CHECKS = [no_server_fault, status_code_conformance, content_type_conformance, response_schema_conformance]


def _fuzz(schema, headers: dict[str, str]) -> list[str]:
    """Every operation, MAX_EXAMPLES generated requests each; returns the failures (route: reason)."""
    failures = []
    for result in schema.get_all_operations():
        operation = result.ok()

        @given(case=operation.as_strategy())
        @settings(max_examples=MAX_EXAMPLES, deadline=None, phases=[Phase.explicit, Phase.generate],
                  suppress_health_check=SLOW_SERVER, database=None)
        def run(case) -> None:
            case.call_and_validate(headers=headers, checks=CHECKS, excluded_checks=[not_a_server_error], timeout=30)

        try:
            run()
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:  # noqa: BLE001 - any failure of a fuzzed call is a finding
            failures.append(f"{operation.label}: {str(exc)[:1500]}")
    return failures


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory):
    with running_server(tmp_path_factory.mktemp("fuzz"), viser=False, min_free_mb=1e12, workspace_grid=5) as (base, _):
        yield schemathesis.openapi.from_url(base + "/openapi.json").exclude(path="/api/live/sse")


def test_every_route_with_the_token_never_fails_the_server(api_schema) -> None:
    failures = _fuzz(api_schema, AUTH)
    assert not failures, "\n\n".join(failures)


def test_every_route_without_the_token_never_fails_the_server(api_schema) -> None:
    failures = _fuzz(api_schema, {})
    assert not failures, "\n\n".join(failures)

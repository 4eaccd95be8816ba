"""A bounded schemathesis run against the service's own OpenAPI schema: no input gives a 5xx.

Generated bodies are rarely images, so this exercises parsing and validation (fast paths), not
recognition; the number of examples per operation is capped to keep the run to seconds.
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from quatrack.testing.scenes import example_store
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings


@pytest.fixture(scope="module")
def api_server():
    with BackgroundServer(Settings(store=example_store(), max_body_bytes=1_000_000)) as srv:
        yield srv


@pytest.fixture(scope="module")
def api_schema(api_server):
    return schemathesis.openapi.from_url(f"{api_server.url}/openapi.json")


def test_no_server_errors(api_schema, api_server):
    """Each operation of the schema, fuzzed; schemathesis' pytest plugin is not used on purpose
    (it ties us to pytest internals), plain hypothesis ``given`` over its strategies instead."""
    operations = [result.ok() for result in api_schema.get_all_operations()]
    assert {op.path for op in operations} >= {"/v1/objects", "/v1/objects/{name}", "/v1/objects/{name}/pose", "/healthz"}
    for op in operations:

        @given(case=op.as_strategy())
        @settings(max_examples=25,  # a budget: each example is an HTTP round trip; the profile does the rest
                  suppress_health_check=list(HealthCheck))
        def fuzz(case):
            response = case.call(timeout=60)
            assert response.status_code < 500, (case.method, case.path, response.status_code, response.text[:300])
            if response.status_code >= 400:
                assert set(response.json()["error"]) == {"code", "message"}

        fuzz()
    # the fuzzing did reach the endpoints (not only the schema loader)
    import httpx

    metrics = httpx.get(f"{api_server.url}/metrics").text
    pose_lines = [ln for ln in metrics.splitlines() if ln.startswith("quatrack_http_requests_total") and "/pose" in ln]
    assert sum(float(ln.split()[-1]) for ln in pose_lines) >= 10, pose_lines
    print("\n".join(pose_lines))

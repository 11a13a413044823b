"""Schemathesis against /openapi.json of a ready server: generated requests never get a 5xx.

CI runs a small bounded budget (GEOLOC_FUZZ_EXAMPLES per operation, default 12); `make fuzz` runs
at least 1,000 requests."""

import os

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error

from tests.api.conftest import Server

pytestmark = pytest.mark.fuzz  # not in `make test-quick`

EXAMPLES = int(os.environ.get("GEOLOC_FUZZ_EXAMPLES", "12"))
MIN_REQUESTS = int(os.environ.get("GEOLOC_FUZZ_MIN_REQUESTS", "0"))


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    with Server(tmp_path_factory.mktemp("fuzz") / "data", fitted_models) as s:
        yield s


def test_no_server_errors(server):
    schema = schemathesis.openapi.from_url(server.url + "/openapi.json")
    operations = [op.ok() for op in schema.get_all_operations()]
    assert len(operations) >= 9
    sent = {"n": 0}
    failures = []
    for op in operations:

        @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy())
        def run(case):
            response = case.call(base_url=server.url, headers={"X-API-Key": server.api_key}, timeout=60)
            sent["n"] += 1
            if response.status_code >= 500:
                failures.append(f"{case.method} {case.formatted_path} -> {response.status_code}: {response.text[:300]}")

        run()
    assert not failures, "\n".join(failures[:10])
    assert sent["n"] >= max(EXAMPLES * len(operations) // 2, MIN_REQUESTS), sent
    print(f"fuzz: {sent['n']} generated requests over {len(operations)} operations, no 5xx")
    _ = not_a_server_error

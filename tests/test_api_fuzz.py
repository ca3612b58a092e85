"""Schema-driven fuzzing of the API's OpenAPI spec (schemathesis + hypothesis).

Every operation gets generated requests, valid and invalid by the schema, over real
HTTP against the real app with a real SQLite file and a real router. None may
answer 5xx, every answer must be one the spec documents with a body that matches
it, and data the schema forbids must be refused.
"""

from __future__ import annotations

import httpx
import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)

from tests.harness import Cluster, start_api


@pytest.fixture(scope="module")
def fuzz_api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api-fuzz")
    with Cluster(tmp) as cluster:
        server = start_api(tmp, cluster.router())
        # Some stored state for the fuzzer to hit: an experiment with a queued run.
        httpx.post(f"{server.url}/experiments", json={"episodes": 12, "seeds": [0, 1]})
        yield server
        server.stop()


CONSTRAINED = {  # operations with a body or parameters the schema restricts
    "POST /experiments",
    "GET /experiments",
    "GET /experiments/{exp_id}/curves",
    "GET /runs/{run_id}/metrics",
    "GET /runs/{run_id}/events",
}
OPERATION_CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    negative_data_rejection,
]


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_no_request_the_schema_allows_or_forbids_gets_a_server_error(fuzz_api, mode):
    schema = schemathesis.openapi.from_url(f"{fuzz_api.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 11
    session = requests.Session()
    calls = []
    for op in operations:

        @given(case=op.as_strategy(generation_mode=mode))
        @settings(
            max_examples=150 if op.label == "POST /experiments" else 25,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def fuzz(case):
            response = case.call_and_validate(
                base_url=fuzz_api.url, session=session, timeout=30, checks=OPERATION_CHECKS
            )
            calls.append((case.operation.label, response.status_code))

        try:
            fuzz()
        except Unsatisfiable:  # the schema forbids nothing here (only free-form strings)
            assert mode == GenerationMode.NEGATIVE and op.label not in CONSTRAINED, op.label
    codes = {code for _, code in calls}
    assert all(code < 500 for code in codes)
    called = {label for label, _ in calls}
    if mode == GenerationMode.POSITIVE:
        assert called == {op.label for op in operations}, "every operation was called"
    else:
        assert called >= CONSTRAINED, "every operation with constraints got forbidden data"
    print(f"{mode}: {len(calls)} calls, status codes {sorted(codes)}")

"""The whole REST API fuzzed from its own OpenAPI schema (schemathesis): no generated request,
valid or not, gets a 5xx. Jobs are recorded, not run, so that the fuzzer's valid bodies start no
training or synthesis; a bounded number of examples per operation keeps it CI-fast
(KGS_FUZZ_EXAMPLES raises it by hand)."""

from __future__ import annotations

import os

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from kgs_backend.main import create_app
from kgs_backend.registry import JobStatus
from kgs_backend.settings import Settings

EXAMPLES = int(os.environ.get("KGS_FUZZ_EXAMPLES", 12))


@pytest.fixture
def api_schema(copy_run):
    # (schemathesis calls the app as the host "localhost" or "testserver")
    app = create_app(Settings(workspace=copy_run.parent.parent, max_upload_mb=1, allowed_hosts=["localhost", "testserver"]))
    jobs = app.state.jobs
    # A job a valid body asks for is queued and stays so: the API is what is fuzzed here.
    jobs.start = lambda table, id_, kind, spec, on_done=None: jobs.ws.update(table, id_, status=JobStatus.QUEUED)
    return schemathesis.openapi.from_asgi("/openapi.json", app)


def test_no_generated_request_gets_a_server_error(api_schema):
    tried = []
    for result in api_schema.get_all_operations():
        operation = result.ok()

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
        def fuzz(case):
            response = case.call()
            assert response.status_code < 500, (case.method, case.formatted_path, case.query, case.body, response.text[:500])

        fuzz()
        tried.append(operation.label)
    assert len(tried) >= 25, tried  # every operation of the API, not a few

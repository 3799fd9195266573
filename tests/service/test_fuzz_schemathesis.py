"""Schema-driven fuzzing with schemathesis: every operation of ``/openapi.json``, seeded examples.

The app under test has a data folder and an API key, and the fuzzer sends the key, so the write
endpoints are reached too. Each operation gets ``MAX_EXAMPLES`` derandomized examples (the same
ones on every run). Checks: no 5xx, every status code documented, the content type and the body
of every answer matching the documented schema of its status, and answers to schema-invalid
requests being errors. (Checks that need state across calls, or that take any schema-valid
request for one that must succeed, do not fit an API whose limits are settings.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import schemathesis
from catalog_testkit import AUTH, writable_settings
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)

from service.api.app import create_app
from service.api.mesh_upload import RAW_MEDIA_FORMATS

MAX_EXAMPLES = 20
# The mesh routes also take the file itself as the body, in these media types: bytes, sent as
# schemathesis sends application/octet-stream.
schemathesis.serializer.alias(list(RAW_MEDIA_FORMATS), "application/octet-stream")
# Batches answer 200 with an error entry per malformed item, by design (one bad item fails alone).
PER_ITEM_ERRORS = {"POST /suggest/batch"}


@schemathesis.check
def negative_data_refused(ctx: Any, response: Any, case: Any) -> bool | None:
    """schemathesis' ``negative_data_rejection``, counting 413 as a refusal too.

    The document carries the server's point-count limit (``maxItems``); a JSON body with more
    points than that is also larger than COMPLEMENTME_MAX_BODY_BYTES, and the body limit refuses
    it (413 ``payload_too_large``) before it is read. Every other status is judged as before.
    """
    if response.status_code == 413:
        return None
    return negative_data_rejection(ctx, response, case)


CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance,
          negative_data_refused]


@pytest.fixture(scope="module")
def api_schema(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Any:
    # schemathesis runs the app's lifespan itself (loading the artifacts once for the module).
    app = create_app(writable_settings(artifacts, tmp_path_factory.mktemp("fuzz-data")))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


schema = schemathesis.pytest.from_fixture("api_schema")


@pytest.fixture(autouse=True)
def _node_id_for_schemathesis(request: pytest.FixtureRequest) -> None:
    # schemathesis' lazy loader renames the test node through ``node._nodeid``, an attribute
    # pytest 9.2 no longer has; give it one (it only changes how the test is reported).
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_schema(case: Any) -> None:
    checks = CHECKS
    if case.operation.label in PER_ITEM_ERRORS:
        checks = [c for c in CHECKS if c is not negative_data_refused]
    case.call_and_validate(headers=AUTH, checks=checks)

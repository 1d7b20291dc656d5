"""Property-based fuzzing of every operation in the OpenAPI schema (schemathesis): no 5xx, ever.

Schemathesis generates requests from the schema -- valid ones and, in the negative phase, ones that
break it -- and checks each response: not a server error, a status code the schema documents, the
documented content type, a body matching the documented schema. One check is left out on purpose:
``positive_data_acceptance`` (schema-valid data must get a 2xx). The plan contract's rules (one-hot
categories, joint limits, the bundle's T range) and "the string is a decodable PNG" cannot be said
in JSON Schema, so schema-valid requests are rightly refused with a 422.

Few examples per operation (``max_examples``) keep the run in seconds; CI runs it on every change.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
import schemathesis
import torch
from hypothesis import HealthCheck, settings
from schemathesis.checks import positive_data_acceptance

from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import export_tiny

from .conftest import STRICT


# The schema is needed when pytest collects (one test per operation), the bundle only when the
# first request starts the app's lifespan (schemathesis runs it, once per app): so the app is made
# at import with the path the module fixture below exports the tiny bundle to. (Schemathesis's
# fixture-based lazy schema does not work with this pytest version.)
BUNDLE = Path(tempfile.gettempdir()) / f"firp-service-fuzz-{os.getpid()}" / "tiny"  # made by _bundle only
APP = create_app(ServiceSettings(bundle=BUNDLE, **STRICT))
schema = schemathesis.openapi.from_dict(APP.openapi())
schema.app = APP


@pytest.fixture(scope="module", autouse=True)
def _bundle():
    torch.manual_seed(0)
    shutil.rmtree(BUNDLE.parent, ignore_errors=True)
    export_tiny(BUNDLE)
    yield
    shutil.rmtree(BUNDLE.parent, ignore_errors=True)


@schema.parametrize()
@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
@pytest.mark.slow
def test_no_server_errors_and_responses_match_the_schema(case):
    response = case.call()
    assert response.status_code < 500, f"{case.method} {case.path}: {response.status_code} {response.text[:500]}"
    case.validate_response(response, excluded_checks=[positive_data_acceptance])


def test_the_schemas_own_examples_reach_the_model():
    """The explicit phase of the fuzzing sends the schema's examples: they must be valid requests that
    the model scores, or every generated request could be a refusal and the fuzzing would prove little.
    (V2 has no examples: its model name in the path is the bundle's, known only once loaded;
    tests/service/test_v2.py covers its success path.)"""
    from fastapi.testclient import TestClient

    components = APP.openapi()["components"]["schemas"]
    with TestClient(APP) as client:
        for path, model in (("/v1/score", "ScoreRequest"), ("/v1/score/batch", "BatchScoreRequest")):
            examples = components[model]["examples"]
            assert examples, model
            for example in examples:
                r = client.post(path, json=example)
                assert r.status_code == 200, (path, r.text[:300])
    registry = APP.state.metrics.registry
    counts = {e: registry.get_sample_value("firp_inference_duration_seconds_count", {"endpoint": e})
              for e in ("/v1/score", "/v1/score/batch")}
    assert all(c and c >= 1 for c in counts.values()), counts

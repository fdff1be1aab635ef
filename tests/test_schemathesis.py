"""Property-based API testing with schemathesis, in process (ASGI, the app with its lifespan on a
leased DB of the real Redis): positive and negative cases generated from the OpenAPI document
for every operation, each response checked for server errors (no 5xx at all), a status the
document lists, its content type, headers and schema, and negative data rejected. At least
1,000 cases in all. Slow tier: a few minutes on 2 cores."""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.generation.modes import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, missing_required_header,
                                               negative_data_rejection, positive_data_acceptance,
                                               response_headers_conformance, response_schema_conformance,
                                               status_code_conformance)

from service.app import create_app
from service.settings import Settings
from tests.harness import RETAILERS, redis_db, redis_url

pytestmark = pytest.mark.slow

EXAMPLES_PER_OPERATION = 50  # per operation and mode: 21 operations x 2 modes
MIN_CASES = 1000
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
          response_schema_conformance, negative_data_rejection, positive_data_acceptance, missing_required_header]


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator:
    with redis_db() as db:
        s = Settings(TRYON_DATA_DIR=Path(tmp_path_factory.mktemp("st")), REDIS_URL=redis_url(db),
                     TRYON_EMBEDDED_WORKER=False, TRYON_RATE_LIMIT_CLIENT=0, TRYON_RATE_LIMIT_RETAILER=0,
                     TRYON_MAX_UPLOAD_BYTES=2_000_000,
                     TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        application = create_app(s)
        with TestClient(application):  # the lifespan: body model, storage, demo garments
            yield application


# Uploads: a schema-valid multipart body can carry any bytes as its file, which the service
# refuses (422) for what is in the file, something a schema cannot express. For these
# operations positive cases must be accepted or refused for a file's content only.
UPLOADS = {"POST /v1/customers", "POST /v1/garments"}
FILE_FIELDS = {"mesh", "meshes", "mhclo", "obj"}


def file_content_refusals_only(ctx, response, case) -> bool | None:
    """A schema-valid upload answered 422 must blame a file field (its content), nothing else."""
    if response.status_code == 422:
        locs = [d.get("loc", []) for d in response.json().get("detail", [])]
        assert locs and all(len(loc) >= 2 and loc[1] in FILE_FIELDS for loc in locs), response.text
    return None


def test_api_conforms(app) -> None:
    """Every operation, positive and negative cases: every check passes on every case."""
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    cases, statuses, failures = 0, Counter(), []
    for result in schema.get_all_operations():
        operation = result.ok()
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):

            @given(operation.as_strategy(generation_mode=mode))
            @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                      suppress_health_check=list(HealthCheck), phases=[Phase.explicit, Phase.generate])
            def run(case: schemathesis.Case) -> None:
                nonlocal cases
                checks = CHECKS
                if operation.label in UPLOADS and mode == GenerationMode.POSITIVE:
                    checks = [c for c in CHECKS if c is not positive_data_acceptance] + [file_content_refusals_only]
                response = case.call_and_validate(checks=checks)
                cases += 1
                statuses[response.status_code] += 1

            try:
                run()
            except Unsatisfiable:  # no negative case exists (an operation without parameters)
                continue
            except (Exception, BaseExceptionGroup) as exc:  # noqa: BLE001 - collected: every operation is tried
                failures.append(f"{operation.label} ({mode.value}): {type(exc).__name__}: {str(exc)[:1500]}")
    print(f"schemathesis: {cases} cases, statuses {dict(sorted(statuses.items()))}, {len(failures)} failures")
    assert not failures, "\n\n".join(failures)
    assert cases >= MIN_CASES and not [s for s in statuses if s >= 500], (cases, statuses)

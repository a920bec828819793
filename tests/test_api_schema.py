"""Property-based run of the OpenAPI description (schemathesis): no request, valid or not, makes the
server answer 5xx.  Bounded: few examples per operation, no shrinking, a deadline per example."""
from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, settings
from schemathesis.checks import not_a_server_error

from api.app import create_app
from bench.storage import open_database
from tests.api_support import ADMIN, TOKENS, register_bench


def build_app(tmp_dir):
    from bench.commands.service import import_dataset
    from tests.test_api_http import synthetic_dataset

    db = open_database(f"sqlite:///{tmp_dir / 'schema.sqlite'}")
    register_bench(db, "bench1")
    rid = import_dataset(db, synthetic_dataset(n=400), "G-001")
    from bench.storage import queries
    from bench.fit.catalog import fit_model
    from bench.storage.export import run_dataset
    ds = run_dataset(rid, db)
    with db.session() as s:
        queries.save_fits(s, "G-001", [rid], [fit_model("static", ds, "x")], accepted=True)
    return create_app(db, tokens=TOKENS)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    return build_app(tmp_path_factory.mktemp("schema"))


def test_no_server_errors(app):
    """Every operation, a few generated cases each (valid and invalid inputs), as admin: never 5xx."""
    from hypothesis import given

    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [r.ok() for r in schema.get_all_operations()]
    assert len(operations) >= 20
    failures, calls, statuses = [], [0], {}
    for op in operations:
        @given(case=op.as_strategy())
        @settings(max_examples=6, phases=[Phase.explicit, Phase.generate], deadline=None, derandomize=True,
                  suppress_health_check=list(HealthCheck), database=None)
        def check(case):
            if isinstance(case.query, dict) and case.query.get("follow") in (True, "true", "True"):
                case.query["max_wait_s"] = 1      # a followed SSE stream lasts until the run ends
            calls[0] += 1
            response = case.call(headers=ADMIN)
            statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
            try:
                case.validate_response(response, checks=[not_a_server_error])
            except Exception as exc:  # noqa: BLE001 - collect every operation's failure, then report
                failures.append(f"{op.method.upper()} {op.path}: {str(exc)[:300]}")
                raise

        try:
            check()
        except Exception:  # noqa: BLE001 - recorded in failures
            pass
    print(statuses)
    assert not failures, "\n".join(failures)
    assert calls[0] >= 3 * len(operations)
    assert statuses.get(200, 0) + statuses.get(201, 0) > 0 and statuses.get(422, 0) > 0, statuses

"""Property-based run of the whole OpenAPI description (schemathesis) with every check it has: no
server error, every status code, content type, header and body shape as documented (problem+json
errors included), schema-invalid data refused, schema-valid data accepted (or refused for the state of
the stored data: 404 / 409), methods and authentication enforced.  As a viewer, an operator and with
no token.  Bounded: a few examples per operation, no shrinking, no example database."""
from __future__ import annotations

import pytest
import schemathesis
from schemathesis import GenerationMode
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis.checks import CHECKS, load_all_checks

from api.app import create_app
from api.schemas import MODEL_FORMAT
from bench.storage import open_database
from tests.api_support import OPERATOR, TOKENS, VIEWER, register_bench

EXAMPLES = 6
PRINCIPALS = {"viewer": VIEWER, "operator": OPERATOR, "no token": {}}


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


def model_names():
    """Values of the documented ``gyrobench-model`` format: a registered model or a formula over the
    signals (bench.fit.formula grammar)."""
    from bench.fit.catalog import NAMED_MODELS

    signals = st.sampled_from(["t1", "t2", "dt1", "(t1-t2)", "(t1-25)"])
    formula = st.builds(lambda terms, p: " + ".join(f"{t}^{p}" if p > 1 else t for t in terms),
                        st.lists(signals, min_size=1, max_size=3, unique=True), st.integers(1, 3))
    return st.one_of(st.sampled_from(sorted(NAMED_MODELS)), formula)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    return build_app(tmp_path_factory.mktemp("schema"))


def test_openapi_all_checks_viewer_operator_no_token(app):
    load_all_checks()
    checks = CHECKS.get_all()
    schemathesis.openapi.format(MODEL_FORMAT, model_names())
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [r.ok() for r in schema.get_all_operations()]
    assert len(operations) >= 20
    failures, calls, statuses = [], [0], {}
    for who, headers in PRINCIPALS.items():
        for op, mode in [(op, mode) for op in operations for mode in GenerationMode]:
            @given(case=op.as_strategy(generation_mode=mode))
            @settings(max_examples=EXAMPLES, phases=[Phase.explicit, Phase.generate], deadline=None,
                      derandomize=True, suppress_health_check=list(HealthCheck), database=None)
            def check(case):
                if isinstance(case.query, dict) and case.query.get("follow") in (True, "true", "True"):
                    case.query["max_wait_s"] = 1      # a followed SSE stream lasts until the run ends
                calls[0] += 1
                response = case.call(headers=headers)
                statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
                try:
                    case.validate_response(response, checks=checks, headers=headers)
                except BaseException as exc:  # noqa: BLE001 - collect every operation's failure, then report
                    failures.append(f"{who}, {mode.value} data: {op.method.upper()} {op.path}: {str(exc)[:600]}")
                    raise

            try:
                check()
            except BaseException:  # noqa: BLE001 - recorded in failures
                pass
    print(statuses)
    assert not failures, "\n".join(failures)
    assert calls[0] >= 2 * len(operations) * len(PRINCIPALS)
    for code in (200, 401, 403, 404, 422):
        assert statuses.get(code, 0) > 0, statuses

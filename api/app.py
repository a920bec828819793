"""The operator service's HTTP API (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``).

``create_app(db=None, *, database_url=None, tokens=None, stale_after_s=15.0)`` builds the app: ``db`` is an
open ``bench.storage.Database`` (else one is opened from ``database_url`` / ``BENCH_DATABASE_URL``);
``tokens`` is ``{token: role}`` or the ``BENCH_TOKENS`` text (default: the environment variable).

The API only writes requests (queued runs, control requests, fit and analysis requests) and reads
state; the bench workers (``bench.worker``) execute runs.  Run it with ``bench serve`` or
``uvicorn --factory api.app:app_from_env``.
"""
from __future__ import annotations

from fastapi import Depends, FastAPI
from fastapi.responses import RedirectResponse

from api import dashboard, problems
from api.auth import parse_tokens, tokens_from_env
from api.routers import fits, meta, runs
from bench.storage.db import Database, open_database

DESCRIPTION = """Gyro thermal-calibration bench: queue and control runs, read their state and data,
fit temperature models, read coefficients by gyro ID.

Authentication: `Authorization: Bearer <token>`; tokens and roles (viewer, operator, admin) come from
`BENCH_TOKENS` (`role:token` pairs separated by commas).  Errors are `application/problem+json`."""


def create_app(db: Database | None = None, *, database_url: str | None = None,
               tokens: dict[str, str] | str | None = None, stale_after_s: float = 15.0,
               sse_poll_s: float = 0.5) -> FastAPI:
    if db is None:
        db = open_database(database_url)
    if tokens is None:
        token_map = tokens_from_env()
    elif isinstance(tokens, str):
        token_map = parse_tokens(tokens)
    else:
        token_map = dict(tokens)
    app = FastAPI(title="Gyro bench operator API", version="1.0", description=DESCRIPTION,
                  dependencies=[Depends(problems.reject_unknown_query)])
    app.state.db = db
    app.state.tokens = token_map
    app.state.stale_after_s = stale_after_s
    app.state.sse_poll_s = sse_poll_s
    from bench.metrics import api_registry
    app.state.metrics_registry = api_registry(db)
    problems.install(app)
    app.include_router(runs.router)
    app.include_router(fits.router)
    app.include_router(meta.router)
    app.include_router(dashboard.router)
    problems.document_problems(app)

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/ui/", status_code=307)

    return app


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory api.app:app_from_env``: database (``BENCH_DATABASE_URL``), tokens
    (``BENCH_TOKENS``) and the worker staleness limit (``BENCH_STALE_AFTER_S``, wall seconds, default 15)
    from the environment (``bench.settings``)."""
    from bench.settings import load_settings

    return create_app(stale_after_s=load_settings().stale_after_s)

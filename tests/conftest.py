"""Shared fixtures.

PostgreSQL: tests of the PostgreSQL path run against the server at 127.0.0.1:5432 (override with
BENCH_TEST_PG_URL).  When CI=true and the server is unreachable they FAIL; elsewhere they skip.
Each test process (the suite runs in three, pytest-xdist) gets its own database, dropped at the end;
tests whose services list every bench or job take a fresh one of their own (``pg_fresh_url``).
"""
from __future__ import annotations

import os
import uuid

import pytest

os.environ.setdefault("W1THERMSENSOR_NO_KERNEL_MODULE", "1")
# One BLAS thread in the test process and in every process it starts (workers, API servers): CI runs
# on 2 cores with 2 CPU hogs beside the suite, where multi-threaded OpenBLAS spin-waits (a 900x900
# Cholesky: 0.55 s with 2 threads, 0.01 s with one, at load average 4).  Set before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

PG_ADMIN_URL = os.environ.get("BENCH_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")

# The test processes take whole files (``--dist loadfile``); a long file handed out last keeps one
# process busy after the others are done.  xdist hands the files out by their number of tests, most
# first, and keeps collection order only among files with as many tests: this order (the longest files,
# measured, about 30 s to 300 s each of one process's time, longest first) breaks those ties and sets
# the order when the suite runs in one process.
LONGEST_FILES_FIRST = (
    "test_closeloop_corpus.py", "test_referee4.py", "test_referee5.py", "test_closeloop_heldout.py",
    "test_sim_lockstep.py", "test_api_process.py", "test_sigstop_drill.py", "test_jobs_drill.py",
    "test_closeloop.py", "test_referee3.py", "test_api_schema.py", "test_dashboard_analyses.py",
    "test_api_serve.py",
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def _pg_unreachable(reason: str):
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"PostgreSQL required in CI but unreachable: {reason}")
    pytest.skip(f"PostgreSQL unreachable: {reason}")


def _admin(url: str):
    import sqlalchemy as sa

    return sa.create_engine(url, isolation_level="AUTOCOMMIT", connect_args={"connect_timeout": 5})


def _create_database(admin, prefix: str) -> str:
    """Create an empty database on ``admin``'s server; its URL."""
    import sqlalchemy as sa

    name = f"{prefix}_{uuid.uuid4().hex[:10]}"
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    return admin.url.render_as_string(hide_password=False).rsplit("/", 1)[0] + "/" + name


def _drop_database(admin, url: str) -> None:
    """Drop the database at ``url`` (its remaining connections ended first), then the admin engine."""
    import sqlalchemy as sa

    name = url.rsplit("/", 1)[1]
    with admin.connect() as conn:
        conn.execute(sa.text(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :n AND pid <> pg_backend_pid()"),
            {"n": name})
        conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}"'))
    admin.dispose()


@pytest.fixture(scope="session")
def pg_url():
    """URL of a fresh, empty PostgreSQL database for this test process."""
    try:
        admin = _admin(PG_ADMIN_URL)
        url = _create_database(admin, "bench_test")
    except Exception as exc:  # noqa: BLE001 - any connection failure is "unreachable"
        _pg_unreachable(str(exc).splitlines()[0])
    yield url
    _drop_database(admin, url)


@pytest.fixture()
def pg_fresh_url(pg_url):
    """A fresh PostgreSQL database for one test, dropped after it: for tests whose services list every
    bench or job in their database (the session's ``pg_url`` database is shared by the tests of one
    test process, in whatever order they run)."""
    admin = _admin(pg_url)
    url = _create_database(admin, "bench_one")
    yield url
    _drop_database(admin, url)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db(request, tmp_path):
    """An empty database per test: a SQLite file, or an own schema in the session's PostgreSQL database."""
    from bench.storage import open_database

    if request.param == "sqlite":
        database = open_database(f"sqlite:///{tmp_path / 'test.sqlite'}")
    else:
        database = open_database(request.getfixturevalue("pg_url"), schema=f"t_{uuid.uuid4().hex[:8]}")
    yield database
    database.dispose()

"""Database opening and migrations (SQLite and PostgreSQL)."""
from __future__ import annotations

import uuid

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect

from bench.storage import StorageError, StorageUnavailable, open_database
from bench.storage.db import head_revision
from bench.storage.models import Base
from tests.test_storage_support import db  # noqa: F401 - fixture

EXPECTED_TABLES = {"gyros", "benches", "runs", "steps", "events", "frame_cursors", "frame_chunks", "frame_seconds",
                   "probe_readings", "telemetry", "segments", "gaps", "suspensions", "fits", "alembic_version"}


def test_migrations_up_from_empty_reach_head_and_match_models(db):
    assert db.current_revision() == head_revision()
    assert EXPECTED_TABLES <= set(inspect(db.engine).get_table_names())   # other areas add tables too
    with db.engine.connect() as conn:
        diffs = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diffs == [], f"models and migrations differ: {diffs}"


def test_open_again_is_a_no_op(db):
    again = open_database(db.url)
    try:
        assert again.current_revision() == head_revision()
    finally:
        again.dispose()


def test_fresh_sqlite_file_gets_pragmas(tmp_path):
    database = open_database(f"sqlite:///{tmp_path / 'sub' / 'fresh.sqlite'}", busy_timeout_ms=1234)
    try:
        with database.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 1234
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2   # FULL
        assert database.current_revision() == head_revision()
    finally:
        database.dispose()


def test_bad_urls_give_typed_errors(tmp_path):
    with pytest.raises(StorageError, match="not valid"):
        open_database("not a url")
    with pytest.raises(StorageError, match="not supported"):
        open_database("mysql://x@localhost/db")
    with pytest.raises(StorageUnavailable, match="cannot open database"):
        open_database("postgresql+psycopg://postgres@127.0.0.1:1/nothing")


def test_env_url_is_the_default(tmp_path, monkeypatch):
    monkeypatch.setenv("BENCH_DATABASE_URL", f"sqlite:///{tmp_path / 'env.sqlite'}")
    database = open_database()
    try:
        assert database.url.endswith("env.sqlite") and (tmp_path / "env.sqlite").exists()
    finally:
        database.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_engine_url(request, tmp_path):
    """(url, schema) of an empty database: an SQLite file, or a fresh schema in the session PG database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'mig.sqlite'}", None
        return
    from sqlalchemy import create_engine, text
    url = request.getfixturevalue("pg_url")
    schema = f"mig_{uuid.uuid4().hex[:8]}"
    yield url, schema
    eng = create_engine(url)
    with eng.begin() as conn:
        conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
    eng.dispose()


def test_per_second_rows_are_converted_to_blocks_and_back(empty_engine_url):
    from sqlalchemy import text
    from bench.storage import migrate, queries, second_means
    from bench.storage.db import make_engine

    url, schema = empty_engine_url
    engine = make_engine(url, schema=schema)
    migrate(engine, "0002_service")
    fields = ("n", "n_invalid", "sum_dt", "sum_gx", "sum_gy", "sum_gz", "sum_ax", "sum_ay", "sum_az",
              "n_temp", "sum_temp")
    seconds = [1_700_000_003, 1_700_000_004, 1_700_000_020]
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO runs (procedure, parameters, config_snapshot, status, operator, created_at, "
                          "progress) VALUES ('old', '{}', '{}', 'completed', '', CURRENT_TIMESTAMP, 1)"))
        run = conn.execute(text("SELECT max(id) FROM runs")).scalar_one()
        for k, sec in enumerate(seconds):
            values = {"n": 10 + k, "n_invalid": k, "sum_dt": 5.0, "sum_gx": 0.1 * (k + 1), "sum_gy": -0.2,
                      "sum_gz": 0.3, "sum_ax": 0.0, "sum_ay": 0.0, "sum_az": 10.0 + k, "n_temp": 10 + k,
                      "sum_temp": 250.0 + k}
            conn.execute(text(f"INSERT INTO frame_seconds (run_id, second, {', '.join(fields)}) VALUES "
                              f"(:run, :sec, {', '.join(':' + f for f in fields)})"), {"run": run, "sec": sec, **values})
    migrate(engine, "head")
    db = open_database(url, schema=schema)
    try:
        sm = second_means(db, run)
        assert list(sm.second) == seconds and list(sm.n) == [10, 11, 12] and list(sm.n_invalid) == [0, 1, 2]
        assert sm.gyro[1] == pytest.approx([0.2 / 11, -0.2 / 11, 0.3 / 11])
        assert sm.temperature_c[2] == pytest.approx(252.0 / 12) and sm.freq_hz is None
        with db.session() as s:
            assert queries.get_run(s, run).procedure == "old"
    finally:
        db.dispose()
    from alembic import command
    from bench.storage.db import alembic_config
    with engine.begin() as conn:
        command.downgrade(alembic_config(conn), "0002_service")
    with engine.connect() as conn:
        back = conn.execute(text("SELECT second, n, sum_gx, sum_fx FROM frame_seconds ORDER BY second")).all()
    assert [(r[0], r[1], r[3]) for r in back] == [(s, 10 + k, None) for k, s in enumerate(seconds)]
    assert back[2][2] == pytest.approx(0.3)
    engine.dispose()

"""Database opening and migrations (SQLite and PostgreSQL)."""
from __future__ import annotations

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
    assert set(inspect(db.engine).get_table_names()) == EXPECTED_TABLES
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

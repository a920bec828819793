"""Alembic environment of the runs database.

Used programmatically by ``bench.storage.db.migrate`` (which passes an open connection in
``config.attributes["connection"]``); also usable from the command line with
``alembic -c bench/storage/migrations/alembic.ini upgrade head`` and ``BENCH_DATABASE_URL`` set.
"""
from __future__ import annotations

from alembic import context

from bench.storage.models import Base

config = context.config
target_metadata = Base.metadata


def _run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata,
                      render_as_batch=connection.dialect.name == "sqlite", compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    from bench.storage.db import default_url, make_engine
    engine = make_engine(config.get_main_option("sqlalchemy.url") or default_url())
    try:
        with engine.begin() as conn:
            _run(conn)
    finally:
        engine.dispose()


if context.is_offline_mode():
    raise SystemExit("offline (--sql) migrations are not supported; run against a database")
run_migrations_online()

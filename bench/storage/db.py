"""Opening the runs database: engine, connection settings and programmatic Alembic migration.

* SQLite (default, a file): every connection gets ``journal_mode=WAL`` (readers never block the
  writer), ``busy_timeout`` (wait for a lock instead of failing at once), ``foreign_keys=ON`` and
  ``synchronous=FULL`` (a committed batch survives power loss), set in a ``connect`` event.
* PostgreSQL by URL (``postgresql+psycopg://user@host:port/db``); an optional ``schema`` puts every
  table (and Alembic's version table) in that schema through ``search_path`` - tests use a fresh
  schema per session.
* ``open_database`` upgrades the schema to Alembic head programmatically; the Alembic scripts ship
  inside the package (``bench/storage/migrations``), no ``alembic.ini`` needed in the CWD.
"""
from __future__ import annotations

import re
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from sqlalchemy import Engine, create_engine, event, inspect, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from bench.settings import DEFAULT_SQLITE_PATH  # noqa: F401  (re-exported)
from bench.storage.errors import StorageError, StorageUnavailable

ENV_URL = "BENCH_DATABASE_URL"
MIGRATIONS_DIR = Path(__file__).with_name("migrations")
_SCHEMA_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,62}$")
_MIGRATION_LOCK_KEY = 0x6779726F   # pg advisory lock key ("gyro") serialising concurrent upgrades


def default_url() -> str:
    """``$BENCH_DATABASE_URL`` if set, else an SQLite file ``var/bench.sqlite`` under the CWD."""
    from bench.settings import load_settings

    return load_settings().database_url_or_default


def make_engine(url: str, *, schema: str | None = None, busy_timeout_ms: int = 30_000,
                echo: bool = False) -> Engine:
    """An engine with the connection settings described in the module docstring (no migration)."""
    try:
        parsed = make_url(url)
    except ArgumentError as exc:
        raise StorageError(f"database URL {url!r} is not valid: {exc}") from None
    backend = parsed.get_backend_name()
    if schema is not None and not _SCHEMA_RE.match(schema):
        raise StorageError(f"schema name {schema!r} is not a plain SQL identifier")
    if backend == "sqlite":
        if schema is not None:
            raise StorageError("a schema can only be given for PostgreSQL, not for SQLite")
        db_path = parsed.database
        if db_path and db_path != ":memory:" and not db_path.startswith("file:"):
            Path(db_path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(parsed, echo=echo, connect_args={"check_same_thread": False,
                                                                 "timeout": busy_timeout_ms / 1000})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record) -> None:
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA synchronous=FULL")
            cur.close()
        return engine
    if backend == "postgresql":
        engine = create_engine(parsed, echo=echo, pool_pre_ping=True,
                               connect_args={"connect_timeout": 5})
        if schema is not None:
            @event.listens_for(engine, "connect")
            def _search_path(dbapi_conn, _record) -> None:
                cur = dbapi_conn.cursor()
                cur.execute(f'CREATE SCHEMA IF NOT EXISTS "{schema}"')
                cur.execute(f'SET search_path TO "{schema}"')
                cur.close()
                dbapi_conn.commit()
        return engine
    raise StorageError(f"database URL {url!r}: backend {backend!r} is not supported (sqlite or postgresql)")


@dataclass
class Database:
    """An open runs database: ``engine`` and ``sessionmaker`` (``expire_on_commit=False``)."""

    url: str
    engine: Engine
    sessionmaker: sessionmaker[Session]
    schema: str | None = None

    @property
    def dialect(self) -> str:
        return self.engine.dialect.name

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session in a transaction: committed on success, rolled back on error."""
        with self.sessionmaker.begin() as session:
            yield session

    def dispose(self) -> None:
        self.engine.dispose()

    def current_revision(self) -> str | None:
        from alembic.runtime.migration import MigrationContext
        with self.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    def size_bytes(self) -> int:
        """Bytes on disk used by the database (SQLite: file + WAL after a checkpoint;
        PostgreSQL: ``pg_total_relation_size`` of every table, i.e. heap + TOAST + indexes)."""
        if self.dialect == "sqlite":
            with self.engine.connect() as conn:
                conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
                pages = conn.exec_driver_sql("PRAGMA page_count").scalar_one()
                free = conn.exec_driver_sql("PRAGMA freelist_count").scalar_one()
                size = conn.exec_driver_sql("PRAGMA page_size").scalar_one()
            return int((pages - free) * size)
        return self.tables_size_bytes(list(inspect(self.engine).get_table_names()))

    def tables_size_bytes(self, tables: list[str]) -> int:
        """Bytes used by the named tables (SQLite: dbstat virtual table; PG: pg_total_relation_size)."""
        with self.engine.connect() as conn:
            if self.dialect == "sqlite":
                total = 0
                for table in tables:
                    names = [table] + [r[0] for r in conn.exec_driver_sql(
                        "SELECT name FROM sqlite_master WHERE type='index' AND tbl_name=?", (table,))]
                    for name in names:
                        total += conn.exec_driver_sql(
                            "SELECT coalesce(sum(pgsize), 0) FROM dbstat WHERE name=?", (name,)).scalar_one()
                return int(total)
            total = 0
            for table in tables:
                total += conn.execute(text("SELECT pg_total_relation_size(CAST(:t AS regclass))"),
                                      {"t": table}).scalar_one()
            return int(total)


def alembic_config(connection=None):
    """An Alembic ``Config`` pointing at the packaged migration scripts (optionally bound to a
    connection, which ``migrations/env.py`` then uses)."""
    from alembic.config import Config
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def head_revision() -> str:
    from alembic.script import ScriptDirectory
    heads = ScriptDirectory.from_config(alembic_config()).get_heads()
    if len(heads) != 1:
        raise StorageError(f"migration scripts have {len(heads)} heads {heads}; expected exactly one")
    return heads[0]


def migrate(engine: Engine, revision: str = "head") -> None:
    """Upgrade the schema to ``revision`` (Alembic ``upgrade``), skipping the work when already there.

    On PostgreSQL a transaction-scoped advisory lock serialises processes that migrate at once.
    """
    from alembic import command
    from alembic.runtime.migration import MigrationContext

    target = head_revision() if revision == "head" else revision
    with engine.connect() as conn:
        if MigrationContext.configure(conn).get_current_revision() == target:
            return
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _MIGRATION_LOCK_KEY})
        command.upgrade(alembic_config(conn), revision)


def open_database(url: str | None = None, *, schema: str | None = None, migrate_to_head: bool = True,
                  busy_timeout_ms: int = 30_000, echo: bool = False) -> Database:
    """Open (and by default migrate to head) the runs database.

    ``url``: SQLAlchemy URL; ``None`` -> ``$BENCH_DATABASE_URL`` or ``sqlite:///var/bench.sqlite``.
    Raises ``StorageUnavailable`` when the server cannot be reached, ``StorageError`` for a bad URL.
    """
    url = url or default_url()
    engine = make_engine(url, schema=schema, busy_timeout_ms=busy_timeout_ms, echo=echo)
    try:
        if migrate_to_head:
            migrate(engine)
        else:
            with engine.connect():
                pass
    except OperationalError as exc:
        engine.dispose()
        raise StorageUnavailable(f"cannot open database {make_url(url).render_as_string(hide_password=True)}: "
                                 f"{str(exc.orig).strip().splitlines()[0] if exc.orig else exc}") from None
    return Database(url=url, engine=engine, sessionmaker=sessionmaker(engine, expire_on_commit=False),
                    schema=schema)

"""Helpers shared by the command modules: loading data by CSV path or run ID, clean error exits."""
from __future__ import annotations

import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import typer

from bench.errors import BenchError
from bench.fit.base import Dataset
from bench.jsonsafe import jsonable as clean_floats  # noqa: F401  (strict JSON for CLI output)


def fail(message: str, code: int = 2) -> NoReturn:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    raise typer.Exit(code)


DB_HELP = "database URL (default $BENCH_DATABASE_URL or sqlite:///var/bench.sqlite)"


def db_option():
    """The ``--db URL`` option every command that touches the database takes."""
    return typer.Option(None, "--db", help=DB_HELP)


def load_dataset(spec: str, db_url: str | None = None) -> Dataset:
    """A measured-data CSV path, or the ID of a stored run (exported the same way ``bench export`` does)
    from the database ``db_url`` (default: ``$BENCH_DATABASE_URL`` or the SQLite file)."""
    from bench.fit.csvio import read_csv

    path = Path(spec)
    if path.exists():
        return read_csv(path)
    if spec.isdigit():
        from bench.storage.db import open_database
        from bench.storage.export import run_dataset   # the stored run as a measured-data Dataset
        return run_dataset(int(spec), open_database(db_url))
    fail(f"{spec!r} is neither an existing CSV file nor a run ID")


def write_json(path: str, doc: Any) -> None:
    text = json.dumps(doc, indent=2, allow_nan=False, default=_default)
    if path == "-":
        sys.stdout.write(text + "\n")
        return
    from bench.files import write_text_atomic

    write_text_atomic(path, text + "\n")


def quantity(value: Any, unit: str, digits: int = 4) -> str:
    """``value`` with ``digits`` significant digits and its unit (``0.01234 deg/h``); ``–`` when missing."""
    if value is None or not isinstance(value, (int, float)) or value != value:
        return "–"
    return f"{value:.{digits}g} {unit}"


def seconds(value: float) -> str:
    """A wall duration for progress lines: ``0.42 s``, ``3.1 s``, ``75 s``."""
    return f"{value:.2g} s" if value < 10 else f"{value:.0f} s"


@contextmanager
def step(text: str):
    """One step of a long command, on stderr: a spinner with the elapsed time on a terminal, else a line
    when it starts; then a line saying how long it took.  Keeps stdout for the command's result."""
    t0 = time.monotonic()
    if sys.stderr.isatty():
        from rich.console import Console

        with Console(stderr=True).status(f"{text}…"):
            yield
    else:
        typer.echo(f"{text}…", err=True)
        yield
    typer.echo(f"{text}: done in {seconds(time.monotonic() - t0)}", err=True)


def _default(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def guarded(fn):
    """Turn the package's own errors into a one-line message and exit code 2."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (BenchError, ValueError, KeyError) as exc:
            fail(str(exc).strip("'\""))
    return wrapper

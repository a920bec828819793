"""Helpers shared by the command modules: loading data by CSV path or run ID, clean error exits."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, NoReturn

import typer

from bench.errors import BenchError
from bench.fit.base import Dataset
from bench.jsonsafe import jsonable as clean_floats  # noqa: F401  (strict JSON for CLI output)


def fail(message: str, code: int = 2) -> NoReturn:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    raise typer.Exit(code)


def load_dataset(spec: str) -> Dataset:
    """A measured-data CSV path, or the ID of a stored run (exported the same way ``bench export`` does)."""
    from bench.fit.csvio import read_csv

    path = Path(spec)
    if path.exists():
        return read_csv(path)
    if spec.isdigit():
        from bench.storage.export import run_dataset   # the stored run as a measured-data Dataset
        return run_dataset(int(spec))
    fail(f"{spec!r} is neither an existing CSV file nor a run ID")


def write_json(path: str, doc: Any) -> None:
    text = json.dumps(doc, indent=2, allow_nan=False, default=_default)
    if path == "-":
        sys.stdout.write(text + "\n")
        return
    tmp = Path(path + ".tmp")
    tmp.write_text(text + "\n")
    tmp.replace(path)


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

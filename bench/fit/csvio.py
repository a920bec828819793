"""Measured-data CSV, version 1: reader and writer (the only I/O of the fitting core).

Format (issue "measured-data CSV v1"):

* Optional leading metadata lines ``# key: value`` (``gyro_id``, ``gyro_type``, ``latitude_deg``,
  ``sample_period_s``, ``channel_probes`` and any other key).  ``channel_probes`` maps each channel to
  its own temperature probe (``# channel_probes: x=t1,y=t2,z=t3``) and is read into
  ``meta["channel_probes"]`` as a dict (every other value stays text).  A leading ``#`` line without
  ``key:`` is a free note; notes
  are joined with newlines into ``meta["notes"]`` (the writer emits ``meta["notes"]`` as ``# notes: ...``
  lines, one per note line, so a read/write/read cycle gives the same ``meta``).
* One header row, then data rows, comma separated.
* Columns: ``time_s`` (required, seconds, strictly increasing, never empty); one or more ``gyro_<ch>``
  (deg/h, as output: Earth rate *not* removed); one or more ``temp_<name>`` (C); optional
  ``freq_<ch>`` (Hz), ``orientation`` (three letters from E W N S U D: directions of body x, y, z, a
  right-handed frame; absent column = ``NUE`` everywhere, empty cell = missing), ``power`` (0/1),
  ``chamber_pv``, ``chamber_sp`` (C), ``table_rate_dps``.  Any other column name is refused.
* An empty numeric field is a missing value (NaN).  ``nan``/``inf`` text is refused.

Rows are parsed by pyarrow's CSV reader (C++, correctly rounded float parsing); when it or any check
fails, a plain ``csv``-module pass re-reads the rows to name the exact problem.
A bad file raises ``bench.errors.DataFormatError`` naming the line (1-based, as in an editor) and the
column; nothing is returned half-read.  Round trip is exact: floats are written with Python's
shortest round-trip ``repr``; NaN is written as an empty field.

Public API::

    read_csv(source, *, text=None) -> Dataset        # source: path (or a name when text is given)
    parse_csv_text(text, *, source="<text>") -> Dataset
    write_csv(dataset, path) -> None                 # atomic (temp file + rename)
    format_csv(dataset) -> str
    ORIENTATION_DEFAULT = DEFAULT_ORIENTATION; validate_orientation(code) -> str
"""
from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

import numpy as np

from bench.errors import DataFormatError
from bench.files import write_text_atomic
from bench.fit.base import Dataset, format_channel_probes, parse_channel_probes
from bench.signal.geometry import DEFAULT_ORIENTATION, validate_canonical_code

ORIENTATION_DEFAULT = DEFAULT_ORIENTATION
FIXED_NUMERIC = ("power", "chamber_pv", "chamber_sp", "table_rate_dps")
PREFIXES = ("gyro_", "temp_", "freq_")
_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_]*)\s*:\s?(.*)$")
_NUMERIC_META = ("latitude_deg", "sample_period_s")


def validate_orientation(code: str) -> str:
    """Return ``code`` if it is an upper-case right-handed orientation code (e.g. ``NUE``), else raise
    ValueError (``bench.signal.geometry`` is the one definition of a valid code)."""
    return validate_canonical_code(code)


def _check_column_name(name: str) -> str | None:
    """None if ``name`` is a valid column name, else the reason."""
    if name in ("time_s", "orientation") or name in FIXED_NUMERIC:
        return None
    for prefix in PREFIXES:
        if name.startswith(prefix):
            rest = name[len(prefix):]
            if rest and _NAME_RE.match(rest):
                return None
            return f"{prefix}<name> needs a name of letters, digits or _"
    return ("unknown column (allowed: time_s, gyro_<ch>, temp_<name>, freq_<ch>, orientation, "
            + ", ".join(FIXED_NUMERIC) + ")")


def read_csv(source: str | os.PathLike, *, text: str | None = None) -> Dataset:
    """Read a measured-data CSV v1 file (or ``text`` labelled ``source``) into a ``Dataset``."""
    if text is None:
        try:
            text = Path(source).read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise DataFormatError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", source=str(source)) from None
    return parse_csv_text(text, source=str(source))


def parse_csv_text(text: str, *, source: str = "<text>") -> Dataset:
    lines = text.splitlines()
    meta: dict[str, str] = {}
    notes: list[str] = []
    i = 0
    while i < len(lines) and (lines[i].startswith("#") or not lines[i].strip()):
        line = lines[i]
        if line.startswith("#"):
            m = _META_RE.match(line)
            if m:
                key, value = m.group(1), m.group(2).rstrip()
                if key == "notes":
                    notes.append(value)
                elif key in meta:
                    raise DataFormatError(f"metadata key {key!r} given twice", line=i + 1, source=source)
                else:
                    if key in _NUMERIC_META:
                        try:
                            if not np.isfinite(float(value)):
                                raise ValueError
                        except ValueError:
                            raise DataFormatError(f"metadata {key!r} must be a finite number, got {value!r}",
                                                  line=i + 1, source=source) from None
                    if key == "channel_probes":
                        try:
                            meta[key] = parse_channel_probes(value)
                        except ValueError as exc:
                            raise DataFormatError(str(exc), line=i + 1, source=source) from None
                    else:
                        meta[key] = value
            else:
                notes.append(line[1:].strip())
        i += 1
    if notes:
        meta["notes"] = "\n".join(notes)
    if "latitude_deg" in meta and not -90.0 <= float(meta["latitude_deg"]) <= 90.0:
        raise DataFormatError("metadata 'latitude_deg' outside [-90, 90]", source=source)
    if i >= len(lines):
        raise DataFormatError("no header row", line=i + 1, source=source)
    header_line = i + 1
    header = next(csv.reader([lines[i]]))
    header = [h.strip() for h in header]
    seen: set[str] = set()
    for name in header:
        reason = _check_column_name(name)
        if reason:
            raise DataFormatError(reason, line=header_line, column=name, source=source)
        if name in seen:
            raise DataFormatError("duplicate column", line=header_line, column=name, source=source)
        seen.add(name)
    if "time_s" not in seen:
        raise DataFormatError("required column time_s missing", line=header_line, source=source)
    if not any(h.startswith("gyro_") for h in header):
        raise DataFormatError("need at least one gyro_<ch> column", line=header_line, source=source)
    if not any(h.startswith("temp_") for h in header):
        raise DataFormatError("need at least one temp_<name> column", line=header_line, source=source)

    fast = _fast_columns("\n".join(lines[i + 1:]), header)
    if fast is not None:
        return Dataset(fast, meta)
    body = lines[i + 1:]           # slow path: exact line/column of the first problem
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    ncol = len(header)
    for k, row in enumerate(csv.reader(body)):
        lineno = header_line + 1 + k
        if not row or (len(row) == 1 and not row[0].strip()):
            continue  # blank line
        if len(row) != ncol:
            raise DataFormatError(f"{len(row)} fields, header has {ncol}", line=lineno, source=source)
        rows.append(row)
        line_numbers.append(lineno)
    cols_text = list(zip(*rows)) if rows else [() for _ in header]
    linenos = np.asarray(line_numbers, dtype=np.int64)

    columns: dict[str, np.ndarray] = {}
    for name, values in zip(header, cols_text):
        if name == "orientation":
            arr = np.array([v.strip() for v in values], dtype=object)
            for code in set(arr.tolist()):
                if code == "":
                    continue
                try:
                    validate_orientation(code)
                except ValueError as exc:
                    bad = int(np.flatnonzero(arr == code)[0])
                    raise DataFormatError(str(exc), line=int(linenos[bad]), column=name, source=source) from None
            columns[name] = arr.astype(str) if len(arr) else np.array([], dtype=str)
            continue
        columns[name] = _parse_numeric(name, values, linenos, source)

    t = columns["time_s"]
    missing_t = np.flatnonzero(np.isnan(t))
    if missing_t.size:
        raise DataFormatError("time_s must not be empty", line=int(linenos[missing_t[0]]), column="time_s",
                              source=source)
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        raise DataFormatError("time_s not strictly increasing", line=int(linenos[back[0] + 1]), column="time_s",
                              source=source)
    if "power" in columns:
        p = columns["power"]
        bad = np.flatnonzero(~np.isnan(p) & (p != 0) & (p != 1))
        if bad.size:
            raise DataFormatError("power must be 0 or 1", line=int(linenos[bad[0]]), column="power", source=source)
    return Dataset(columns, meta)


def _fast_columns(body: str, header: list[str]) -> dict[str, np.ndarray] | None:
    """Parse the rows with pyarrow's CSV reader (C++, correctly rounded floats).  Returns None when
    anything is off, so that the slow path can name the exact line and column of the problem."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    types = {name: (pa.string() if name == "orientation" else pa.float64()) for name in header}
    try:
        table = pacsv.read_csv(
            io.BytesIO(body.encode("utf-8")),
            read_options=pacsv.ReadOptions(column_names=header, use_threads=False),
            parse_options=pacsv.ParseOptions(newlines_in_values=False),
            convert_options=pacsv.ConvertOptions(column_types=types, null_values=[""], strings_can_be_null=False,
                                                 quoted_strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowTypeError, UnicodeError):
        return None
    cols: dict[str, np.ndarray] = {}
    for name in header:
        col = table.column(name)
        if name == "orientation":
            arr = np.asarray(col.to_pylist(), dtype=str) if table.num_rows else np.array([], dtype=str)
            for code in set(arr.tolist()) - {""}:
                try:
                    validate_orientation(code)
                except ValueError:
                    return None
            cols[name] = arr
            continue
        arr = col.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        nan = np.isnan(arr)
        if int(nan.sum()) != col.null_count or np.isinf(arr).any():   # "nan"/"inf" text: refuse (slow path)
            return None
        cols[name] = arr
    t = cols["time_s"]
    if np.isnan(t).any() or np.any(np.diff(t) <= 0):
        return None
    if "power" in cols:
        p = cols["power"]
        if np.any(~np.isnan(p) & (p != 0) & (p != 1)):
            return None
    return cols


def _parse_numeric(name: str, values: tuple[str, ...], linenos: np.ndarray, source: str) -> np.ndarray:
    if not values:
        return np.array([], dtype=np.float64)
    arr = np.char.strip(np.asarray(values, dtype=str))
    empty = arr == ""
    arr[empty] = "0"
    try:
        out = arr.astype(np.float64)
    except ValueError:
        out = None
    if out is not None:
        bad = np.flatnonzero(~np.isfinite(out))
        if bad.size:
            raise DataFormatError(f"not a finite number: {values[bad[0]].strip()!r}", line=int(linenos[bad[0]]),
                                  column=name, source=source)
        out[empty] = np.nan
        return out
    for k, v in enumerate(arr.tolist()):   # slow path only to locate the bad cell
        try:
            float(v)
        except ValueError:
            raise DataFormatError(f"not a number: {v!r}", line=int(linenos[k]), column=name, source=source) from None
    raise AssertionError("unreachable")  # pragma: no cover


def _format_float_column(col: np.ndarray) -> list[str]:
    return ["" if v != v else repr(v) for v in np.asarray(col, dtype=np.float64).tolist()]


def format_csv(dataset: Dataset) -> str:
    """Render ``dataset`` as CSV v1 text (validates column names, orientation codes, time_s)."""
    names = list(dataset.columns)
    for name in names:
        reason = _check_column_name(name)
        if reason:
            raise DataFormatError(reason, column=name, source="dataset to write")
    if "time_s" not in names:
        raise DataFormatError("required column time_s missing", source="dataset to write")
    order = ["time_s"] + [n for n in names if n != "time_s"]
    out = io.StringIO()
    for key, value in dataset.meta.items():
        if key == "notes":
            for note in str(value).split("\n"):
                out.write(f"# notes: {note}\n")
        elif key == "channel_probes":
            try:
                mapping = parse_channel_probes(value) if isinstance(value, str) else dict(value)
                out.write(f"# channel_probes: {format_channel_probes(mapping)}\n")
            except (TypeError, ValueError) as exc:
                raise DataFormatError(f"metadata 'channel_probes': {exc}", source="dataset to write") from None
        else:
            if "\n" in str(value) or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", key):
                raise DataFormatError(f"metadata {key!r}: key must be an identifier and value one line",
                                      source="dataset to write")
            out.write(f"# {key}: {value}\n")
    out.write(",".join(order) + "\n")
    cols_text = []
    for name in order:
        col = dataset.columns[name]
        if name == "orientation":
            texts = [str(v) for v in col.tolist()]
            for code in set(texts) - {""}:
                try:
                    validate_orientation(code)
                except ValueError as exc:
                    raise DataFormatError(str(exc), column=name, source="dataset to write") from None
            cols_text.append(texts)
        else:
            cols_text.append(_format_float_column(col))
    out.writelines(",".join(r) + "\n" for r in zip(*cols_text))
    return out.getvalue()


def write_csv(dataset: Dataset, path: str | os.PathLike) -> None:
    """Write ``dataset`` to ``path`` atomically (nothing half-written on error)."""
    text = format_csv(dataset)
    # round-trip guard: what we write must read back (catches e.g. non-increasing time_s)
    parse_csv_text(text, source=str(path))
    write_text_atomic(path, text, newline="")

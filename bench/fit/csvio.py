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
* Columns: ``time_s`` (required, seconds, strictly increasing, never empty); ``gyro_<ch>`` (deg/h, as
  output: Earth rate *not* removed) and/or ``freq_<ch>`` (Hz), at least one of them; one or more
  ``temp_<name>`` (C); optional ``orientation`` (three letters from E W N S U D: directions of body x, y, z, a
  right-handed frame; absent column = ``NUE`` everywhere, empty cell = missing), ``power`` (0/1),
  ``chamber_pv``, ``chamber_sp`` (C), ``table_rate_dps``.  Any other column name is refused.
* An empty numeric field is a missing value (NaN).  ``nan``/``inf`` text is refused.
* Plausibility: temperatures (``temp_<name>``, ``chamber_pv``, ``chamber_sp``) within -100..+200 C,
  frequencies > 0; a value outside is refused naming line and column (gyro rates are checked against
  the bench's gyro range by ``bench import``).  A leading UTF-8 byte-order mark is ignored.

Rows are parsed by pyarrow's CSV reader (C++, correctly rounded float parsing); when it or any check
fails, a plain ``csv``-module pass re-reads the rows to name the exact problem.
A bad file raises ``bench.errors.DataFormatError`` naming the line (1-based, as in an editor) and the
column; nothing is returned half-read.  Round trip is exact: floats are written with Python's
shortest round-trip ``repr``; NaN is written as an empty field.

Public API::

    read_csv(source, *, text=None) -> Dataset        # source: path (or a name when text is given)
    CsvStream(path, block_bytes=...)                 # .meta, .header; iterate: checked batches of columns
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
        except FileNotFoundError:
            raise DataFormatError("file not found", source=str(source)) from None
        except IsADirectoryError:
            raise DataFormatError("is a directory, not a CSV file", source=str(source)) from None
        except OSError as exc:
            raise DataFormatError(f"cannot read: {exc.strerror}", source=str(source)) from None
        except UnicodeDecodeError as exc:
            raise DataFormatError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", source=str(source)) from None
    return parse_csv_text(text, source=str(source))


BOM = "\ufeff"


def _parse_preamble(lines, source: str) -> tuple[dict[str, str], int]:
    """Metadata of the leading ``#`` lines; returns (meta, index of the first other line)."""
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
    if "sample_period_s" in meta and not float(meta["sample_period_s"]) > 0:
        raise DataFormatError("metadata 'sample_period_s' must be > 0", source=source)
    return meta, i


def _parse_header(line: str, header_line: int, source: str) -> list[str]:
    header = [h.strip() for h in next(csv.reader([line]))]
    seen: set[str] = set()
    for name in header:
        reason = _check_column_name(name)
        if reason:
            raise DataFormatError(reason, line=header_line, column=name, source=source)
        if name in seen:
            raise DataFormatError("duplicate column", line=header_line, column=name, source=source)
        seen.add(name)
    if "time_s" not in seen:
        raise DataFormatError(f"required column time_s missing (columns: {', '.join(header)})", line=header_line,
                              source=source)
    if not any(h.startswith(("gyro_", "freq_")) for h in header):
        raise DataFormatError(f"need at least one gyro_<ch> or freq_<ch> column (columns: {', '.join(header)})",
                              line=header_line, source=source)
    if not any(h.startswith("temp_") for h in header):
        raise DataFormatError(f"need at least one temp_<name> column (columns: {', '.join(header)})",
                              line=header_line, source=source)
    return header


def parse_csv_text(text: str, *, source: str = "<text>") -> Dataset:
    lines = text.splitlines()
    if lines and lines[0].startswith(BOM):
        lines[0] = lines[0][len(BOM):]          # a UTF-8 byte-order mark (some spreadsheets write one)
    meta, i = _parse_preamble(lines, source)
    if i >= len(lines):
        raise DataFormatError("no header row", line=i + 1, source=source)
    header_line = i + 1
    header = _parse_header(lines[i], header_line, source)
    body = "\n".join(lines[i + 1:])
    fast = _fast_columns(body, header)
    if fast is not None:
        return Dataset(fast, meta)
    # slow path: the exact line and column of the first problem
    return Dataset(_slow_columns(header, csv.reader(lines[i + 1:]), header_line + 1, source, None), meta)


# plausibility of measured values, per column kind: (low, high) inclusive; None = unbounded
TEMPERATURE_RANGE_C = (-100.0, 200.0)
PLAUSIBLE = {"temp_": TEMPERATURE_RANGE_C, "chamber_pv": TEMPERATURE_RANGE_C, "chamber_sp": TEMPERATURE_RANGE_C}


def _violation(cols: dict[str, np.ndarray], prev_t: float | None) -> tuple[int, str, str] | None:
    """The first problem in parsed columns as (row, column, message), or None.  ``prev_t``: time_s of
    the row before these (streaming), so time stays strictly increasing across batches."""
    problems: list[tuple[int, str, str]] = []
    t = cols["time_s"]
    missing_t = np.flatnonzero(np.isnan(t))
    if missing_t.size:
        problems.append((int(missing_t[0]), "time_s", "time_s must not be empty"))
    tt = t if prev_t is None else np.concatenate([[prev_t], t])
    back = np.flatnonzero(np.diff(tt) <= 0)
    if back.size:
        problems.append((int(back[0]) + (1 if prev_t is None else 0), "time_s", "time_s not strictly increasing"))
    for name, arr in cols.items():
        if name == "orientation":
            continue
        if name == "power":
            bad = np.flatnonzero(~np.isnan(arr) & (arr != 0) & (arr != 1))
            if bad.size:
                problems.append((int(bad[0]), name, "power must be 0 or 1"))
            continue
        if name.startswith("freq_"):
            bad = np.flatnonzero(~(arr > 0) & ~np.isnan(arr))
            if bad.size:
                problems.append((int(bad[0]), name, f"frequency {float(arr[bad[0]])!r} Hz: must be positive"))
            continue
        limits = PLAUSIBLE.get(name) or PLAUSIBLE.get(name[:5])
        if limits is not None:
            lo, hi = limits
            bad = np.flatnonzero((arr < lo) | (arr > hi))
            if bad.size:
                problems.append((int(bad[0]), name, f"{float(arr[bad[0]])!r} C is outside the plausible range "
                                                     f"{lo:g}..{hi:g} C"))
    return min(problems) if problems else None


def _slow_columns(header: list[str], reader, first_line: int, source: str,
                  prev_t: float | None) -> dict[str, np.ndarray]:
    """Parse text rows with the ``csv`` module, raising ``DataFormatError`` at the first bad line."""
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    ncol = len(header)
    for k, row in enumerate(reader):
        lineno = first_line + k
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
    found = _violation(columns, prev_t)
    if found is not None:
        row, column, message = found
        raise DataFormatError(message, line=int(linenos[row]), column=column, source=source)
    return columns


def _table_columns(table, header: list[str]) -> dict[str, np.ndarray] | None:
    """Numpy columns of a pyarrow table read with every column as float64 (orientation as string);
    None when a cell was ``nan``/``inf`` text or an orientation code is invalid."""
    cols: dict[str, np.ndarray] = {}
    for name in header:
        col = table.column(name)
        if name == "orientation":
            arr = col.to_numpy(zero_copy_only=False).astype(str) if table.num_rows else np.array([], dtype=str)
            for code in set(np.unique(arr).tolist()) - {""}:
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
    return cols


def _convert_options(header: list[str]):
    import pyarrow as pa
    import pyarrow.csv as pacsv

    types = {name: (pa.string() if name == "orientation" else pa.float64()) for name in header}
    return pacsv.ConvertOptions(column_types=types, null_values=[""], strings_can_be_null=False,
                                quoted_strings_can_be_null=False)


def _fast_columns(body: str, header: list[str]) -> dict[str, np.ndarray] | None:
    """Parse the rows with pyarrow's CSV reader (C++, correctly rounded floats).  Returns None when
    anything is off, so that the slow path can name the exact line and column of the problem."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    try:
        table = pacsv.read_csv(
            io.BytesIO(body.encode("utf-8")),
            read_options=pacsv.ReadOptions(column_names=header, use_threads=False),
            parse_options=pacsv.ParseOptions(newlines_in_values=False),
            convert_options=_convert_options(header))
    except (pa.ArrowInvalid, pa.ArrowTypeError, UnicodeError):
        return None
    cols = _table_columns(table, header)
    if cols is None or _violation(cols, None) is not None:
        return None
    return cols


class CsvStream:
    """A measured-data CSV v1 file read in batches of rows, in bounded memory (for ``bench import``).

    Opening reads the metadata and the header (``meta``, ``header``); iterating yields dicts of numpy
    columns, each batch checked as ``read_csv`` checks a whole file (time_s strictly increasing across
    batches too).  The first problem raises ``DataFormatError`` naming the line and column; a caller
    that stores batches must therefore read the whole stream once before storing anything (``check``),
    or be able to undo.  A missing or unreadable file is a one-line ``DataFormatError``.
    """

    def __init__(self, path: str | os.PathLike, *, block_bytes: int = 4 << 20) -> None:
        self.path = Path(path)
        self.source = str(path)
        self.block_bytes = block_bytes
        try:
            fh = open(self.path, "rb")
        except FileNotFoundError:
            raise DataFormatError("file not found", source=self.source) from None
        except IsADirectoryError:
            raise DataFormatError("is a directory, not a CSV file", source=self.source) from None
        except OSError as exc:
            raise DataFormatError(f"cannot read: {exc.strerror}", source=self.source) from None
        with fh:
            lines: list[str] = []
            while True:
                raw = fh.readline()
                if not raw:
                    break
                try:
                    text = raw.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise DataFormatError(f"not UTF-8 text ({exc.reason})", line=len(lines) + 1,
                                          source=self.source) from None
                if not lines and text.startswith(BOM):
                    text = text[len(BOM):]
                lines.append(text.rstrip("\r\n"))
                if not (text.startswith("#") or not text.strip()):
                    break
            self.meta, i = _parse_preamble(lines, self.source)
            if i >= len(lines):
                raise DataFormatError("no header row", line=i + 1, source=self.source)
            self.header_line = i + 1
            self.header = _parse_header(lines[i], self.header_line, self.source)
            self.body_offset = fh.tell()

    def __iter__(self):
        import pyarrow as pa
        import pyarrow.csv as pacsv

        prev_t: float | None = None
        with open(self.path, "rb") as fh:
            fh.seek(self.body_offset)
            try:
                reader = pacsv.open_csv(
                    fh, read_options=pacsv.ReadOptions(column_names=self.header, use_threads=False,
                                                       block_size=self.block_bytes),
                    parse_options=pacsv.ParseOptions(newlines_in_values=False),
                    convert_options=_convert_options(self.header))
                for batch in reader:
                    cols = _table_columns(pa.Table.from_batches([batch]), self.header)
                    if cols is None or _violation(cols, prev_t) is not None:
                        break
                    if len(cols["time_s"]):
                        prev_t = float(cols["time_s"][-1])
                        yield cols
                else:
                    return
            except (pa.ArrowInvalid, pa.ArrowTypeError, UnicodeError):
                pass
        self._raise_first_problem()

    def _raise_first_problem(self, batch_rows: int = 50_000) -> None:
        """Re-read the body with the ``csv`` module, batch by batch, and raise at the first bad line."""
        prev_t: float | None = None
        line = self.header_line + 1
        with open(self.path, "rb") as fh:
            fh.seek(self.body_offset)
            text = io.TextIOWrapper(fh, encoding="utf-8", newline="")
            reader = csv.reader(text)
            while True:
                rows = []
                try:
                    for row in reader:
                        rows.append(row)
                        if len(rows) >= batch_rows:
                            break
                except UnicodeDecodeError as exc:
                    raise DataFormatError(f"not UTF-8 text ({exc.reason})", line=line + len(rows),
                                          source=self.source) from None
                if not rows:
                    break
                cols = _slow_columns(self.header, rows, line, self.source, prev_t)
                if len(cols["time_s"]):
                    prev_t = float(cols["time_s"][-1])
                line += len(rows)
        raise DataFormatError("the fast CSV reader refused this file, the careful one found no problem",
                              source=self.source)

    def check(self) -> int:
        """Read the whole file once; the number of data rows (raises at the first problem)."""
        return sum(len(cols["time_s"]) for cols in self)


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

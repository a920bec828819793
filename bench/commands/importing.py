"""``bench import``: a measured-data CSV (v1) stored as a completed run of procedure ``import``.

All or nothing, in bounded memory:

1. **Check** - the file is read once in batches (``bench.fit.csvio.CsvStream``): format, every cell,
   time_s strictly increasing, plausibility per column (temperatures -100..+200 C, frequencies > 0,
   gyro rates within the frame format's range and the bench's gyro range).  The first problem is a
   ``DataFormatError`` naming the line and the column; nothing has been written.
2. **Store** - only then the run is created and the batches are read again and written through a
   ``FrameWriter`` flushed synchronously after each batch (memory stays at one batch).
3. **Publish** - the run is marked completed.  If storing fails (database error, Ctrl-C), the run and
   every row written for it are deleted (``ON DELETE CASCADE``), so a failed import leaves nothing.
   A process killed while storing (kill -9) leaves its staging run (``live.import == "storing"`` with
   its host and pid); the next import on that host deletes it (``sweep_abandoned_imports``).

Each row becomes one gyro frame: KVH Format A (deg/h -> deg/s, float32 as on the wire), or the HRG
frame when the file has ``freq_<ch>`` columns (frequencies as float64).  The bytes are an encoding of
the imported values, not bytes received from a device, which the run's ``config_snapshot.import`` says.
``temp_<name>`` become probe readings, ``chamber_pv``/``chamber_sp`` chamber telemetry, ``power`` PSU
on/off, and each stretch of constant ``orientation`` a ``record`` segment labelled with it.
"""
from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterable, Iterator
import numpy as np

from bench.errors import DataFormatError

FLOAT32_MAX = float(np.finfo(np.float32).max)


def _gyro_limit_dph(gyro_cfg) -> tuple[float, str]:
    """Largest plausible |rate| in deg/h and where it comes from: the bench's gyro range, never more
    than the frame format can carry (float32 deg/s)."""
    limit_dps = min(float(gyro_cfg.range_dps), FLOAT32_MAX)
    return limit_dps * 3600.0, f"the gyro range of +-{gyro_cfg.range_dps:g} deg/s (bench config gyro.range_dps)"


def check_batch(cols: dict[str, np.ndarray], first_row: int, limit_dph: float, why: str, source: str) -> None:
    """Refuse implausible gyro rates (the reader has checked temperatures, frequencies and time)."""
    for name, arr in cols.items():
        if name.startswith("gyro_"):
            bad = np.flatnonzero(np.abs(arr) > limit_dph)
            if bad.size:
                raise DataFormatError(f"{float(arr[bad[0]])!r} deg/h is outside {why}",
                                      column=name, source=f"{source} (data row {first_row + int(bad[0]) + 1})")


class _Source:
    """Batches of columns, readable twice (check pass, store pass)."""

    def __init__(self, header: list[str], meta: dict[str, str], batches: Callable[[], Iterable[dict]]) -> None:
        self.header, self.meta, self._batches = header, meta, batches

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return iter(self._batches())


def import_csv(db, path, gyro_id: str, *, bench_name: str | None = None, operator: str = "",
               progress: Callable[[int], None] | None = None, block_bytes: int = 1 << 20) -> int:
    """Import the CSV file ``path`` (any size, batches of about ``block_bytes``); returns the run id."""
    from bench.fit.csvio import CsvStream

    stream = CsvStream(path, block_bytes=block_bytes)
    return _import(db, _Source(stream.header, stream.meta, lambda: stream), gyro_id, source=str(path),
                   bench_name=bench_name, operator=operator, progress=progress)


def import_dataset(db, dataset, gyro_id: str, *, source: str = "", bench_name: str | None = None,
                   operator: str = "", progress=None) -> int:
    """Store an in-memory measured-data ``Dataset`` the way ``import_csv`` stores a file."""
    from bench.fit.csvio import _violation

    cols = {k: np.asarray(v) for k, v in dataset.columns.items()}
    if "time_s" not in cols:
        raise DataFormatError("required column time_s missing", source=source or None)
    found = _violation({k: v for k, v in cols.items() if k != "orientation"}, None)
    if found is not None:
        row, column, message = found
        raise DataFormatError(message, column=column, source=f"{source or 'dataset'} (data row {row + 1})")
    return _import(db, _Source(list(cols), dict(dataset.meta), lambda: [cols]), gyro_id, source=source,
                   bench_name=bench_name, operator=operator, progress=progress)


def _bench_config(db, bench_name: str | None):
    from sqlalchemy import select

    from bench.config import BenchConfig, GyroConfig
    from bench.storage.models import Bench

    if bench_name:
        with db.session() as s:
            row = s.scalars(select(Bench).where(Bench.name == bench_name)).first()
            if row is not None and row.config:
                cfg = BenchConfig.model_validate(row.config)
                return cfg.gyro, getattr(cfg, "latitude_deg", None)
    return GyroConfig(), None


def sweep_abandoned_imports(db) -> list[int]:
    """Delete the staging runs of imports whose process died (kill -9, power loss) on this host: an
    import run still ``storing`` whose recorded pid is no longer alive.  Returns the run ids removed.
    Every import calls it first, so a killed import leaves nothing behind for long."""
    from sqlalchemy import select

    from bench.storage.models import Run

    removed = []
    host = socket.gethostname()
    with db.session() as s:
        for run in s.scalars(select(Run).where(Run.procedure == "import", Run.status == "running")):
            live = run.live or {}
            if live.get("import") == "storing" and live.get("host") == host and not _alive(live.get("pid")):
                removed.append(run.id)
                s.delete(run)           # ON DELETE CASCADE: its frames, readings and segments too
    return removed


def _alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except (TypeError, ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def _import(db, src: _Source, gyro_id: str, *, source: str, bench_name: str | None, operator: str,
            progress) -> int:
    from bench.storage import queries
    from bench.storage.models import Run, utcnow

    header = src.header
    gyro_channels = [c for c in ("x", "y", "z") if f"gyro_{c}" in header]
    freq_channels = [c for c in ("x", "y", "z") if f"freq_{c}" in header]
    extra = [h for h in header if h.startswith(("gyro_", "freq_")) and h[5:] not in ("x", "y", "z")]
    if extra:
        raise DataFormatError(f"columns {extra}: only the channels x, y, z map onto a stored gyro frame "
                              f"(columns: {', '.join(header)})", source=source or None)
    if not gyro_channels and not freq_channels:
        raise DataFormatError(f"no gyro_<ch> or freq_<ch> column: nothing measured to store "
                              f"(columns: {', '.join(header)})", source=source or None)
    gyro_cfg, bench_lat = _bench_config(db, bench_name)
    limit_dph, why = _gyro_limit_dph(gyro_cfg)

    # 1. check the whole input before writing anything
    n, first_times = 0, []
    for cols in src:
        check_batch(cols, n, limit_dph, why, source or "dataset")
        t = cols["time_s"]
        first_times += t[:2 - len(first_times)].tolist()
        n += int(t.size)
    if n == 0:
        raise DataFormatError("no data rows", source=source or None)
    meta = dict(src.meta)
    period = float(meta["sample_period_s"]) if "sample_period_s" in meta else (
        first_times[1] - first_times[0] if len(first_times) == 2 else 1.0)
    latitude = float(meta["latitude_deg"]) if "latitude_deg" in meta else (
        bench_lat if bench_lat is not None else None)
    kind = "hrg" if freq_channels else "kvh_a"
    snapshot = {"name": bench_name or "import",
                "gyro": {"frame": kind, "output_units": "deg/s", "channels": gyro_channels,
                         "freq_channels": freq_channels, "range_dps": float(gyro_cfg.range_dps)},
                "import": {"source": source, "rows": n, "meta": meta, "sample_period_s": period,
                           "note": f"frames re-encoded from the CSV values ({kind} layout)"}}
    if latitude is not None:
        snapshot["latitude_deg"] = latitude
    mapping = meta.get("channel_probes") or {}      # the CSV reader gives the parsed dict
    for ch, probe in mapping.items():
        if ch not in gyro_channels or f"temp_{probe}" not in header:
            raise DataFormatError(f"metadata channel_probes: {ch}={probe} names a "
                                  + (f"channel without a gyro_{ch} column" if ch not in gyro_channels
                                     else f"probe without a temp_{probe} column"), source=source or None)
    if mapping:
        snapshot["gyro"]["channel_probes"] = dict(mapping)

    # 2. store (first removing what a killed import on this host left)
    sweep_abandoned_imports(db)
    with db.session() as s:
        queries.ensure_gyro(s, gyro_id, type=meta.get("gyro_type"))
        run = queries.create_run(s, procedure="import", parameters={"source": source, "rows": n},
                                 config_snapshot=snapshot, operator=operator, gyro_id=gyro_id, bench_name=bench_name)
        run.status, run.started_at = "running", utcnow()
        run.live = {"import": "storing", "host": socket.gethostname(), "pid": os.getpid()}
        run_id = run.id
    try:
        _store(db, run_id, src, kind, period, progress)
        # 3. publish
        with db.session() as s:
            r = queries.get_run(s, run_id, for_update=True)
            r.status, r.finished_at, r.progress = "completed", utcnow(), 1.0
            r.live = {"outcome": "completed", "import": True}
            queries.add_event(s, run_id, "imported", f"{n} rows imported from {source or 'CSV'}")
    except BaseException:
        with db.session() as s:           # undo: the run and (ON DELETE CASCADE) every row written for it
            r = s.get(Run, run_id)
            if r is not None:
                s.delete(r)
        raise
    return run_id


def _store(db, run_id: int, src: _Source, kind: str, period: float, progress) -> None:
    from bench.devices.kvh import encode_format_a, encode_hrg
    from bench.interfaces import GyroFrame, ProbeReading
    from bench.storage import FrameWriter

    writer = FrameWriter(db, run_id, frame_kind=kind, nominal_rate_hz=1.0 / period if period > 0 else None,
                         sequence_modulus=None, valid_status=0x7F if kind == "hrg" else 0x77, autostart=False)
    valid_status = 0x7F if kind == "hrg" else 0x77
    probes = [h[5:] for h in src.header if h.startswith("temp_")]
    row = 0
    seg_code, seg_start, last_t = None, None, None
    zero3 = (0.0, 0.0, 0.0)
    try:
        for cols in src:
            m = int(cols["time_s"].size)
            t = cols["time_s"]
            gyro = np.zeros((m, 3))
            for i, c in enumerate("xyz"):
                if f"gyro_{c}" in cols:
                    gyro[:, i] = cols[f"gyro_{c}"] / 3600.0
            freq = None
            if kind == "hrg":
                freq = np.zeros((m, 3))      # a channel the file lacks: 0 Hz, left out on export (snapshot)
                for i, c in enumerate("xyz"):
                    if f"freq_{c}" in cols:
                        freq[:, i] = cols[f"freq_{c}"]
            valid = np.all(np.isfinite(gyro), axis=1)
            gyro = np.nan_to_num(gyro)
            first_temp = cols[f"temp_{probes[0]}"]
            temps = {p: cols[f"temp_{p}"] for p in probes}
            frames = []
            for i in range(m):
                seq = (row + i) % 128
                temp = float(first_temp[i])
                status = valid_status if valid[i] else 0x00
                g = (float(gyro[i, 0]), float(gyro[i, 1]), float(gyro[i, 2]))
                if freq is None:
                    raw = encode_format_a(g, zero3, sequence=seq, temperature_c=temp if temp == temp else 0.0,
                                          status=status)
                    fz = None
                else:
                    fz = (float(freq[i, 0]), float(freq[i, 1]), float(freq[i, 2]))
                    raw = encode_hrg(g, zero3, fz, sequence=seq, temperature_c=temp if temp == temp else 0.0,
                                     status=status)
                frames.append(GyroFrame(float(t[i]), seq, g, zero3, status, temp, raw, fz))
                ti = float(t[i])
                writer.add_probe_readings(ti, [ProbeReading(p, "", float(v), None) if (v := temps[p][i]) == v
                                               else ProbeReading(p, "", None, "missing in CSV") for p in probes])
            if "chamber_pv" in cols or "chamber_sp" in cols:
                pv = cols.get("chamber_pv", np.full(m, np.nan))
                sp = cols.get("chamber_sp", np.full(m, np.nan))
                for i in np.flatnonzero(np.isfinite(pv) | np.isfinite(sp)).tolist():
                    writer.add_telemetry(float(t[i]), "chamber",
                                         chamber_pv=float(pv[i]) if np.isfinite(pv[i]) else None,
                                         chamber_sp=float(sp[i]) if np.isfinite(sp[i]) else None)
            if "power" in cols:
                pw = cols["power"]
                for i in np.flatnonzero(np.isfinite(pw)).tolist():
                    writer.add_telemetry(float(t[i]), "psu", psu_on=bool(pw[i]))
            writer.add_many(frames)
            codes = cols["orientation"] if "orientation" in cols else None
            # segments: stretches of constant orientation (absent column: NUE), bounded half-way between
            # rows so that every row lies well inside its own (stored times are rounded to microseconds)
            for i in range(m):
                code = str(codes[i]) if codes is not None else "NUE"
                ti = float(t[i])
                if code != seg_code:
                    edge = ti - period / 2.0 if last_t is None else (last_t + ti) / 2.0
                    if seg_code is not None:
                        _segment(writer, seg_code, seg_start, edge)
                    seg_code, seg_start = code, edge
                last_t = ti
            writer.flush()           # bounded memory: one batch at a time
            row += m
            if progress is not None:
                progress(m)
        if seg_code is not None:
            _segment(writer, seg_code, seg_start, last_t + period / 2.0)
        writer.close()
    except BaseException:
        writer.abandon()
        raise


def _segment(writer, code: str, t_start: float, t_end: float) -> None:
    """A recorded stretch of the file (every row lies in one, so none is left out when the run is read);
    an empty orientation cell stays unknown."""
    labels = {"source": "import", **({"position": code} if code else {})}
    writer.add_segment("record", t_start, t_end, orientation=code or None, labels=labels)


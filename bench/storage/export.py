"""Aligned columns of a run for ``bench export RUN --format csv|parquet`` and for fitting.

``export_columns`` returns a dict of equal-length numpy arrays, one row per bench second (from the
``frame_seconds`` sums) or per frame:

* ``time_s`` seconds since the run's first frame second, ``bench_time_s`` absolute bench time,
  ``n_frames`` (per-second only: valid frames averaged);
* ``gyro_x/y/z`` in deg/h (the wire unit is taken from the run's config snapshot
  ``gyro.output_units``: deg/s x 3600, rad/s x 180/pi x 3600), ``accel_x/y/z`` in g, ``temp_gyro``
  (device's own sensor), ``freq_x/y/z`` for resonator gyros;
* ``temp_<probe>``: DS18B20 readings interpolated linearly in time between the two valid readings
  around each second (a probe samples a continuous temperature; holding the previous reading would
  delay it by up to a read period, which at an accelerated clock is minutes of bench time); NaN
  where those readings are more than ``max_age_s`` apart or the second lies beyond the last one;
* ``chamber_pv``, ``chamber_sp`` (the target), ``chamber_ramp_sp`` (the set point the controller
  follows now: it moves along a ramp), ``axis1_pos``, ``axis2_pos``, ``psu_v``, ``psu_a``, ``power_w``,
  ``psu_on`` (1/0): nearest previous telemetry sample (NaN when older than ``max_age_s`` or five
  times the device's usual telemetry interval, whichever is longer);
* ``orientation``, ``segment_kind`` (str), ``temp_point_c``, ``repetition``, ``outer_deg``,
  ``inner_deg``: labels of the segment covering the time (the latest-started one if several).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from sqlalchemy import select

from bench.storage.db import Database
from bench.storage.errors import StorageError
from bench.storage.models import Gyro, ProbeReadingRow, Run, Segment, Telemetry
from bench.storage.reader import read_frames, second_means

_TO_DPH = {"deg/s": 3600.0, "rad/s": 180.0 / math.pi * 3600.0, "deg/h": 1.0}


def dph_per_unit(units: str) -> float | None:
    """deg/h per one unit of the gyro's wire output (``deg/s``, ``rad/s``, ``deg/h``); None when unknown."""
    return _TO_DPH.get(units)


def gyro_units(db: Database, run_id: int) -> str:
    with db.session() as s:
        run = s.get(Run, run_id)
        if run is None:
            raise StorageError(f"run {run_id} does not exist")
        gyro_cfg = (run.config_snapshot or {}).get("gyro") or {}
        return str(gyro_cfg.get("output_units", "deg/s"))


def _previous(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray, max_age_s: float) -> np.ndarray:
    """Value of the latest sample at or before each ``t`` (NaN if none or older than max_age_s)."""
    out = np.full(t.shape, np.nan)
    if t_src.size == 0:
        return out
    idx = np.searchsorted(t_src, t, side="right") - 1
    ok = idx >= 0
    ok[ok] &= (t[ok] - t_src[idx[ok]]) <= max_age_s
    out[ok] = v_src[idx[ok]]
    return out


def _interpolated(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Linear interpolation between the samples around each ``t``; NaN across gaps over max_gap_s and
    outside the sampled span (beyond ``max_gap_s`` after the last sample: the previous value)."""
    out = np.full(t.shape, np.nan)
    if t_src.size == 0:
        return out
    out[:] = np.interp(t, t_src, v_src)
    after = np.searchsorted(t_src, t, side="left")           # first sample at or after t
    before = after - 1
    inside = (before >= 0) & (after < t_src.size)
    gap = np.full(t.shape, np.inf)
    gap[inside] = t_src[after[inside]] - t_src[before[inside]]
    exact = (after < t_src.size) & (t_src[np.minimum(after, t_src.size - 1)] == t)
    tail = (after >= t_src.size) & (t - t_src[-1] <= max_gap_s)
    ok = exact | (inside & (gap <= max_gap_s)) | tail
    out[~ok] = np.nan
    # a sample within a microsecond (the resolution of stored frame times) is the value itself, not a
    # slope times the rounding: an imported CSV's probe column reads back exactly
    nearest = np.clip(np.searchsorted(t_src, t), 1, max(1, t_src.size - 1))
    for cand in (nearest - 1, np.minimum(nearest, t_src.size - 1)):
        same = np.abs(t_src[cand] - t) <= 1e-6
        out[same] = v_src[cand[same]]
    return out


def _probe_columns(db: Database, run_id: int, t: np.ndarray, max_age_s: float) -> dict[str, np.ndarray]:
    p = ProbeReadingRow
    with db.engine.connect() as conn:
        rows = conn.execute(select(p.name, p.t, p.celsius).where(p.run_id == run_id, p.celsius.is_not(None))
                            .order_by(p.name, p.t)).all()
    cols: dict[str, np.ndarray] = {}
    by_name: dict[str, list[tuple[float, float]]] = {}
    for name, t_, c in rows:            # one pass over the readings (every 2 s per probe for the whole run)
        by_name.setdefault(name, []).append((t_, c))
    for name in sorted(by_name):
        arr = np.array(by_name[name], dtype=np.float64)
        # a gap counts as a lost probe when it is much longer than this probe's usual read interval
        usual = float(np.median(np.diff(arr[:, 0]))) if len(arr) > 2 else 0.0
        cols[f"temp_{name}"] = _interpolated(arr[:, 0], arr[:, 1], t, max(max_age_s, 5.0 * usual))
    return cols


def _telemetry_columns(db: Database, run_id: int, t: np.ndarray, max_age_s: float) -> dict[str, np.ndarray]:
    tm = Telemetry
    wanted = {"chamber": [("chamber_pv", tm.chamber_pv), ("chamber_sp", tm.chamber_sp),
                          ("chamber_ramp_sp", tm.chamber_ramp_sp)],
              "turntable": [("axis1_pos", tm.axis1_pos), ("axis2_pos", tm.axis2_pos)],
              "psu": [("psu_v", tm.psu_volts), ("psu_a", tm.psu_amps), ("psu_on", tm.psu_on)]}
    cols: dict[str, np.ndarray] = {}
    with db.engine.connect() as conn:
        for device, fields in wanted.items():
            rows = conn.execute(select(tm.t, *[c for _, c in fields]).where(tm.run_id == run_id, tm.device == device)
                                .order_by(tm.t)).all()
            if not rows:
                continue
            arr = np.array([[np.nan if v is None else float(v) for v in r] for r in rows], dtype=np.float64)
            # a sample is stale when much older than this device's usual telemetry interval
            usual = float(np.median(np.diff(arr[:, 0]))) if len(arr) > 2 else 0.0
            for i, (name, _) in enumerate(fields, start=1):
                if np.isfinite(arr[:, i]).any():
                    cols[name] = _previous(arr[:, 0], arr[:, i], t, max(max_age_s, 5.0 * usual))
    if "psu_v" in cols and "psu_a" in cols:
        cols["power_w"] = cols["psu_v"] * cols["psu_a"]
    return cols


def _segment_columns(db: Database, run_id: int, t: np.ndarray) -> dict[str, np.ndarray]:
    with db.session() as s:
        segs = list(s.scalars(select(Segment).where(Segment.run_id == run_id).order_by(Segment.t_start, Segment.id)))
    n = t.size
    orientation = np.full(n, "", dtype=object)
    kind = np.full(n, "", dtype=object)
    temp_point = np.full(n, np.nan)
    repetition = np.full(n, -1, dtype=np.int64)
    outer = np.full(n, np.nan)
    inner = np.full(n, np.nan)
    for seg in segs:          # later-started segments overwrite earlier ones where they overlap
        end = math.inf if seg.t_end is None else seg.t_end
        m = (t >= seg.t_start) & (t < end)
        if not m.any():
            continue
        orientation[m] = seg.orientation or ""
        kind[m] = seg.kind
        temp_point[m] = np.nan if seg.temperature_c is None else seg.temperature_c
        repetition[m] = seg.repetition
        outer[m] = np.nan if seg.outer_deg is None else seg.outer_deg
        inner[m] = np.nan if seg.inner_deg is None else seg.inner_deg
    return {"orientation": orientation.astype(str), "segment_kind": kind.astype(str), "temp_point_c": temp_point,
            "repetition": repetition, "outer_deg": outer, "inner_deg": inner}


def export_columns(db: Database, run_id: int, *, resolution: Literal["second", "frame"] = "second",
                   units: str | None = None, max_age_s: float = 30.0,
                   t_from: float | None = None, t_to: float | None = None) -> dict[str, np.ndarray]:
    """The run's aligned columns (see the module docstring).  Empty arrays when no frames are stored."""
    units = units or gyro_units(db, run_id)
    if units not in _TO_DPH:
        raise StorageError(f"run {run_id}: gyro output unit {units!r} unknown (known: {', '.join(_TO_DPH)})")
    scale = _TO_DPH[units]
    cols: dict[str, np.ndarray] = {}
    if resolution == "second":
        sm = second_means(db, run_id, t_from=t_from, t_to=t_to)
        t = sm.time
        cols["n_frames"] = sm.n
        gyro, accel, temp_gyro, freq = sm.gyro, sm.accel, sm.temperature_c, sm.freq_hz
    elif resolution == "frame":
        fr = read_frames(db, run_id, t_from=t_from, t_to=t_to)
        if fr is None:
            t, gyro, accel, temp_gyro, freq = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), None
        else:
            t, gyro, accel, temp_gyro, freq = fr.time, fr.gyro, fr.accel, fr.temperature_c, fr.freq_hz
            cols["frame_index"] = fr.index
            cols["status"] = fr.status.astype(np.int64)
    else:
        raise ValueError(f"resolution must be 'second' or 'frame', got {resolution!r}")
    t0 = math.floor(t[0]) if t.size else 0.0
    out: dict[str, np.ndarray] = {"time_s": t - t0, "bench_time_s": t}
    out.update(cols)
    for i, axis in enumerate("xyz"):
        out[f"gyro_{axis}"] = gyro[:, i] * scale
    for i, axis in enumerate("xyz"):
        out[f"accel_{axis}"] = accel[:, i]
    out["temp_gyro"] = temp_gyro
    if freq is not None:
        for i, axis in enumerate("xyz"):
            out[f"freq_{axis}"] = freq[:, i]
    out.update(_probe_columns(db, run_id, t, max_age_s))
    out.update(_telemetry_columns(db, run_id, t, max_age_s))
    out.update(_segment_columns(db, run_id, t))
    return out


def write_parquet(columns: dict[str, np.ndarray], path: str | Path, metadata: dict[str, str] | None = None) -> Path:
    """Write columns to a Parquet file (atomically: temp file then rename)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    path = Path(path)
    table = pa.table({name: pa.array(values.tolist() if values.dtype.kind == "U" else values)
                      for name, values in columns.items()})
    if metadata:
        table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                               **{k.encode(): str(v).encode() for k, v in metadata.items()}})
    tmp = path.with_name(path.name + ".tmp")
    pq.write_table(table, tmp)
    tmp.replace(path)
    return path


def export_parquet(db: Database, run_id: int, path: str | Path, *,
                   resolution: Literal["second", "frame"] = "second") -> Path:
    columns = export_columns(db, run_id, resolution=resolution)
    return write_parquet(columns, path, {"run_id": str(run_id), "resolution": resolution, "gyro_unit": "deg/h"})


# ---------------------------------------------------------------- measured-data dataset of a run
def _segment_label_mask(db: Database, run_id: int, t: np.ndarray, where: dict) -> np.ndarray:
    """Rows whose bench time lies in a segment whose labels hold every ``where`` item."""
    with db.session() as s:
        segs = list(s.scalars(select(Segment).where(Segment.run_id == run_id)))
    mask = np.zeros(t.shape, dtype=bool)
    for seg in segs:
        labels = seg.labels or {}
        if all(labels.get(k) == v for k, v in where.items()):
            end = math.inf if seg.t_end is None else seg.t_end
            mask |= (t >= seg.t_start) & (t < end)
    return mask


def run_dataset(run_id: int, db: Database | None = None, *, latitude_deg: float | None = None,
                where: dict | None = None, recorded_only: bool = True,
                max_age_s: float | None = None):
    """A stored run as a measured-data ``bench.fit.base.Dataset`` (the columns of measured-data CSV v1).

    Rows: 1-s means (``export_columns(resolution="second")``) of the seconds with valid frames, only
    those inside recorded segments when ``recorded_only`` (and, with ``where``, only segments whose
    labels hold every item, e.g. ``{"set": "model"}``).  Columns: ``time_s`` (s since the run's first
    frame second), ``gyro_<ch>`` (deg/h, Earth rate not removed), ``temp_<probe>`` (DS18B20; the
    gyro's own sensor as ``temp_gyro`` only when no probe was read), ``freq_<ch>`` (HRG),
    ``orientation`` (segment label, empty = unknown), ``power`` (PSU output 1/0), ``chamber_pv``,
    ``chamber_sp``.  Metadata (everything a fit needs, so export -> import -> fit equals the fit by run
    ID): run_id, procedure, gyro_id, gyro_type (the gyro's stored type, else the frame kind),
    gyro_frame, sample_period_s = 1, bench_time0_s (bench time of ``time_s`` 0), ``channel_probes`` (dict
    channel -> its own probe, from the config snapshot's ``gyro.channel_probes``, when the bench declared
    it) and ``latitude_deg``
    (argument, else the run's config snapshot) whenever it is known; a fit leaves rows without an
    orientation out of Earth-rate removal and says so.  An imported run gives only the gyro and
    frequency channels its file had.  ``db`` defaults to ``open_database()`` (``$BENCH_DATABASE_URL`` or
    the default SQLite file).
    ``max_age_s`` (previous-sample hold of probes/telemetry) defaults to the run's recorded engine
    periods (``runs.live["engine_config"]``) x 2, at least 30 s.
    """
    from bench.fit.base import Dataset
    from bench.storage.db import open_database

    own = db is None
    if own:
        db = open_database()
    try:
        with db.session() as s:
            run = s.get(Run, int(run_id))
            if run is None:
                raise StorageError(f"run {run_id} does not exist in {db.url}")
            snapshot = dict(run.config_snapshot or {})
            live = dict(run.live or {})
            meta = {"run_id": str(run.id), "procedure": run.procedure, "sample_period_s": "1"}
            if run.gyro_id:
                meta["gyro_id"] = run.gyro_id
                gyro = s.get(Gyro, run.gyro_id)
                if gyro is not None and gyro.type:
                    meta["gyro_type"] = str(gyro.type)
        gyro_cfg = snapshot.get("gyro") or {}
        if gyro_cfg.get("frame"):
            meta["gyro_frame"] = str(gyro_cfg["frame"])
            meta.setdefault("gyro_type", str(gyro_cfg["frame"]))
        imported = "import" in snapshot      # an imported run holds only the channels its file had
        recorded_channels = gyro_cfg.get("channels") if imported else None
        freq_channels = gyro_cfg.get("freq_channels") if imported else None
        if gyro_cfg.get("channel_probes"):
            meta["channel_probes"] = {str(ch): str(p) for ch, p in gyro_cfg["channel_probes"].items()}
        if max_age_s is None:
            ecfg = live.get("engine_config") or {}
            periods = [float(ecfg.get(k, 0.0) or 0.0) for k in ("telemetry_period_s", "probe_period_s", "max_tick_s")]
            max_age_s = max(30.0, 2.0 * max(periods))
        cols = export_columns(db, int(run_id), resolution="second", max_age_s=max_age_s)
        t = cols["bench_time_s"]
        keep = cols["n_frames"] > 0
        if recorded_only:
            keep &= cols["segment_kind"] != ""
        if where:
            keep &= _segment_label_mask(db, int(run_id), t, where)
        out: dict[str, np.ndarray] = {"time_s": cols["time_s"][keep]}
        if keep.any():
            meta["bench_time0_s"] = repr(float(t[0] - cols["time_s"][0]))
        for name in sorted(cols):
            if (name.startswith("freq_") and (freq_channels is None or name[5:] in freq_channels)) or (
                    name.startswith("gyro_") and (recorded_channels is None or name[5:] in recorded_channels)):
                out[name] = cols[name][keep]
        probes = [n for n in sorted(cols) if n.startswith("temp_") and n not in ("temp_gyro", "temp_point_c")]
        for name in probes or (["temp_gyro"] if "temp_gyro" in cols else []):
            out[name] = cols[name][keep]
        out["orientation"] = np.asarray(cols["orientation"][keep]).astype(str)
        if "psu_on" in cols:
            out["power"] = cols["psu_on"][keep]
        for name in ("chamber_pv", "chamber_sp"):
            if name in cols:
                out[name] = cols[name][keep]
        lat = latitude_deg if latitude_deg is not None else snapshot.get("latitude_deg")
        if lat is not None:       # rows without an orientation are left out of Earth-rate removal by the fit
            meta["latitude_deg"] = repr(float(lat))
        return Dataset(out, meta)
    finally:
        if own:
            db.dispose()

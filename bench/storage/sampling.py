"""How well a run was sampled: for each device the number of readings and the median / largest
interval between them in bench seconds.

    {"probes": {"readings": n, "median_interval_s": s, "max_interval_s": s, "per_probe": {...}},
     "chamber": {...}, "turntable": {...}, "psu": {...}, "gyro": {...}}

Probes count read cycles (one time stamp per read of the whole bus; ``per_probe`` has the valid
readings of each probe); the gyro counts stored frames (intervals between consecutive frame times,
so a link gap shows as ``max_interval_s``).  Intervals are None with fewer than two readings.

A multi-gyro run (the parent, which stores the chamber, table and supply) also has ``units``: for each
fixture slot, the probes and gyro frames its gyro's run stored, as above.
"""
from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from sqlalchemy import select

from bench.storage.db import Database
from bench.storage.models import FrameChunk, ProbeReadingRow, Run, Telemetry
from bench.storage import codec

TELEMETRY_DEVICES = ("chamber", "turntable", "psu")


def interval_stats(times: np.ndarray) -> dict[str, Any]:
    times = np.unique(np.asarray(times, dtype=float))
    d = np.diff(times)
    return {"readings": int(times.size),
            "median_interval_s": float(np.median(d)) if d.size else None,
            "max_interval_s": float(d.max()) if d.size else None}


_CACHE: dict[tuple[int, int], tuple[float, dict[str, Any]]] = {}
_CACHE_LOCK = threading.Lock()


def sampling_summary(db: Database, run_id: int, *, max_age_s: float = 0.0) -> dict[str, Any]:
    """The summary (see the module docstring); with ``max_age_s`` a summary computed for the same run
    less than that many wall seconds ago is returned again (the API is polled while a run grows)."""
    key = (id(db), int(run_id))
    if max_age_s > 0:
        with _CACHE_LOCK:
            hit = _CACHE.get(key)
        if hit is not None and time.monotonic() - hit[0] < max_age_s:
            return hit[1]
    out = _summary(db, run_id)
    if not _has_readings(out):
        # nothing stored yet costs nothing to count again: a run that has just started is not shown
        # as having no readings for max_age_s while its plots fill (at x1000 bench speed, 5 wall seconds
        # are more than an hour of data)
        return out
    with _CACHE_LOCK:
        if len(_CACHE) > 256:
            _CACHE.clear()
        _CACHE[key] = (time.monotonic(), out)
    return out


def _has_readings(summary: dict[str, Any]) -> bool:
    devices = [summary.get(k) or {} for k in ("probes", "gyro", *TELEMETRY_DEVICES)]
    devices += [d for unit in (summary.get("units") or {}).values() for d in unit.values()]
    return any(d.get("readings") for d in devices)


def _summary(db: Database, run_id: int) -> dict[str, Any]:
    out = _own_summary(db, run_id)
    with db.engine.connect() as conn:
        units = conn.execute(select(Run.slot, Run.id).where(Run.parent_id == run_id).order_by(Run.slot)).all()
    if units:
        out["units"] = {}
        for slot, child_id in units:
            child = _own_summary(db, child_id)
            out["units"][slot] = {"probes": child["probes"], "gyro": child["gyro"]}
    return out


def _own_summary(db: Database, run_id: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    with db.engine.connect() as conn:
        rows = conn.execute(select(ProbeReadingRow.t, ProbeReadingRow.name, ProbeReadingRow.celsius)
                            .where(ProbeReadingRow.run_id == run_id)).all()
        probes = interval_stats(np.array([r[0] for r in rows]))
        per: dict[str, list[float]] = {}
        for t, name, celsius in rows:          # (Row.t is SQLAlchemy's tuple view, not the column)
            if celsius is not None:
                per.setdefault(name, []).append(t)
        probes["per_probe"] = {name: interval_stats(np.array(ts)) for name, ts in sorted(per.items())}
        out["probes"] = probes
        for device in TELEMETRY_DEVICES:
            ts = conn.execute(select(Telemetry.t).where(Telemetry.run_id == run_id,
                                                        Telemetry.device == device)).scalars().all()
            out[device] = interval_stats(np.array(ts))
        chunks = conn.execute(select(FrameChunk.t_first, FrameChunk.dt_us).where(FrameChunk.run_id == run_id)
                              .order_by(FrameChunk.first_index)).all()
    times = (np.concatenate([codec.unpack_times(c.t_first, c.dt_us) for c in chunks]) if chunks
             else np.zeros(0))
    gyro = {"readings": int(times.size), "median_interval_s": None, "max_interval_s": None}
    if times.size > 1:
        d = np.diff(times)
        gyro.update(median_interval_s=float(np.median(d)), max_interval_s=float(d.max()))
    out["gyro"] = gyro
    return out

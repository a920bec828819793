"""JSON documents the API answers with, built from the database rows."""
from __future__ import annotations

import datetime as dt
import math
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from bench.storage import queries
from bench.storage.db import Database
from bench.storage.models import (Bench, FrameCursor, Gap, ProbeReadingRow, Run, RunRequest, Step, Suspension,
                                  Telemetry, utcnow)

TERMINAL = ("completed", "aborted", "failed")


def iso(value: dt.datetime | None) -> str | None:
    if value is None:
        return None
    if value.tzinfo is None:
        value = value.replace(tzinfo=dt.timezone.utc)
    return value.isoformat()


def fresh(heartbeat: dt.datetime | None, stale_after_s: float) -> bool:
    if heartbeat is None:
        return False
    if heartbeat.tzinfo is None:
        heartbeat = heartbeat.replace(tzinfo=dt.timezone.utc)
    return (utcnow() - heartbeat).total_seconds() <= stale_after_s


def finite(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, (np.floating,)):
        return finite(float(x))
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def run_summary(run: Run, bench_name: str | None, stale_after_s: float) -> dict[str, Any]:
    live = run.live or {}
    active = run.status in ("running", "paused", "stopping", "suspended")
    return {
        "id": run.id, "procedure": run.procedure, "gyro_id": run.gyro_id, "bench": bench_name,
        "status": run.status, "outcome": live.get("outcome"), "operator": run.operator,
        "created_at": iso(run.created_at), "start_at": iso(run.start_at), "started_at": iso(run.started_at),
        "finished_at": iso(run.finished_at),
        "progress_percent": round(100.0 * run.progress, 2),
        "step_index": run.current_step,
        "eta_utc": live.get("eta_utc") if active else None,
        "worker": run.worker, "worker_alive": fresh(run.heartbeat_at, stale_after_s) if active else None,
        "heartbeat_at": iso(run.heartbeat_at), "error": run.error,
        "parent_id": run.parent_id, "slot": run.slot, "status_reason": live.get("status_reason"),
    }


def run_detail(session: Session, db: Database, run: Run, bench_name: str | None, stale_after_s: float) -> dict[str, Any]:
    doc = run_summary(run, bench_name, stale_after_s)
    live = run.live or {}
    prog = live.get("progress") or {}
    steps = session.scalars(select(Step).where(Step.run_id == run.id).order_by(Step.index)).all()
    current = next((s for s in steps if s.index == run.current_step), None)
    doc["parameters"] = run.parameters
    doc["step"] = ({"index": current.index, "kind": current.kind, "status": current.status,
                    "n_steps": len(steps)} if current is not None else None)
    doc["remaining_bench_s"] = finite(prog.get("remaining_bench_s")) if run.status not in TERMINAL else 0.0
    doc["elapsed_bench_s"] = finite(prog.get("elapsed_bench_s"))
    doc["estimated_total_bench_s"] = finite((live.get("summary") or {}).get("total_bench_s"))
    doc["steps"] = [{"index": s.index, "kind": s.kind, "status": s.status, "started_t": s.started_t,
                     "finished_t": s.finished_t} for s in steps]
    doc["gaps"] = [{"t_from": g.t_from, "t_to": g.t_to, "reason": g.reason, "frames_missing": g.frames_missing}
                   for g in session.scalars(select(Gap).where(Gap.run_id == run.id).order_by(Gap.t_from))]
    doc["frames_lost"] = int(sum(g["frames_missing"] or 0 for g in doc["gaps"]))
    doc["bench_seconds_lost"] = float(sum(g["t_to"] - g["t_from"] for g in doc["gaps"]))
    doc["suspensions"] = [{"t_from": s.t_from, "t_to": s.t_to, "reason": s.reason}
                          for s in session.scalars(select(Suspension).where(Suspension.run_id == run.id)
                                                   .order_by(Suspension.t_from))]
    doc["pending_requests"] = [{"id": r.id, "command": r.command, "requested_at": iso(r.created_at)}
                               for r in session.scalars(select(RunRequest).where(
                                   RunRequest.run_id == run.id, RunRequest.consumed_at.is_(None))
                                   .order_by(RunRequest.id))]
    doc["fits"] = live.get("fits")
    doc["latest"] = latest_readings(session, db, run.id)
    from bench.storage.sampling import sampling_summary

    doc["sampling"] = sampling_summary(db, run.id, max_age_s=0.0 if run.status in TERMINAL else 5.0)
    doc["units"] = [unit_state(session, db, unit) for unit in queries.unit_runs(session, run.id)]
    return doc


def unit_state(session: Session, db: Database, unit: Run) -> dict[str, Any]:
    """One gyro of a multi-gyro run: its own run's state, gaps and latest readings."""
    gaps = session.scalars(select(Gap).where(Gap.run_id == unit.id).order_by(Gap.t_from)).all()
    return {"slot": unit.slot, "run_id": unit.id, "gyro_id": unit.gyro_id, "status": unit.status,
            "outcome": (unit.live or {}).get("outcome"), "error": unit.error,
            "gaps": [{"t_from": g.t_from, "t_to": g.t_to, "reason": g.reason} for g in gaps],
            "bench_seconds_lost": float(sum(g.t_to - g.t_from for g in gaps)),
            "latest": latest_readings(session, db, unit.id)}


def latest_readings(session: Session, db: Database, run_id: int) -> dict[str, Any]:
    """The newest stored value of each signal: chamber, table, PSU, every probe and the gyro's last 1-s mean."""
    out: dict[str, Any] = {}
    tm = Telemetry
    for device in ("chamber", "turntable", "psu"):
        row = session.scalars(select(tm).where(tm.run_id == run_id, tm.device == device)
                              .order_by(tm.t.desc()).limit(1)).first()
        if row is None:
            continue
        if device == "chamber":
            out["chamber"] = {"t": row.t, "pv_c": row.chamber_pv, "setpoint_c": row.chamber_sp,
                              "ramp_setpoint_c": row.chamber_ramp_sp, "mode": row.chamber_mode,
                              "alarm": row.chamber_alarm}
        elif device == "turntable":
            out["turntable"] = {"t": row.t, "axis1_deg": row.axis1_pos, "axis1_dps": row.axis1_rate,
                                "axis2_deg": row.axis2_pos, "axis2_dps": row.axis2_rate}
        else:
            out["psu"] = {"t": row.t, "volts": row.psu_volts, "amps": row.psu_amps, "on": row.psu_on}
    p = ProbeReadingRow
    t_last = session.scalar(select(func.max(p.t)).where(p.run_id == run_id))
    if t_last is not None:
        out["probes"] = {"t": t_last, "celsius": {r.name: r.celsius for r in session.scalars(
            select(p).where(p.run_id == run_id, p.t == t_last))},
            "faults": {r.name: r.fault for r in session.scalars(
                select(p).where(p.run_id == run_id, p.t == t_last, p.fault.is_not(None)))}}
    cur = session.get(FrameCursor, run_id)
    if cur is not None and cur.t_last is not None:
        gyro: dict[str, Any] = {"t_last_frame": cur.t_last, "frames": cur.next_index}
        try:
            from bench.storage.export import dph_per_unit, gyro_units
            from bench.storage.reader import second_means
            sm = second_means(db, run_id, t_from=cur.t_last - 3.0, t_to=cur.t_last)
            rows = np.flatnonzero(np.isfinite(np.asarray(sm.gyro, float)).any(axis=1)) if len(sm.time) else []
            if len(rows):                              # the newest second that has a value (not a partial one)
                units = gyro_units(db, run_id)
                scale = dph_per_unit(units)            # deg/h, as the plots and the exports show it
                last = int(rows[-1])
                gyro["mean_1s"] = {"t": float(sm.time[last]), "output_unit": "deg/h" if scale else units,
                                   "gyro": [finite(float(v) * (scale or 1.0)) for v in sm.gyro[last]],
                                   "temperature_c": finite(float(sm.temperature_c[last]))}
        except Exception as exc:  # noqa: BLE001 - the summary is optional; report why it is missing
            gyro["mean_1s_error"] = f"{type(exc).__name__}: {exc}"
        out["gyro"] = gyro
    return out


def bench_doc(session: Session, bench: Bench, stale_after_s: float) -> dict[str, Any]:
    cfg = bench.config or {}
    devices = {
        "chamber": {k: (cfg.get("chamber") or {}).get(k) for k in ("transport", "address", "unit_id")},
        "turntable": {k: (cfg.get("turntable") or {}).get(k) for k in ("url", "axes")},
        "gyro": {k: (cfg.get("gyro") or {}).get(k) for k in ("url", "frame", "data_rate_hz", "channels")},
        "probes": dict((cfg.get("probes") or {}).get("probes") or {}),
        "psu": {k: (cfg.get("psu") or {}).get(k) for k in ("url", "voltage_v", "current_limit_a")},
    }
    active = session.scalars(select(Run).where(Run.bench_id == bench.id,
                                               Run.status.in_(("running", "paused", "stopping", "suspended")))
                             .order_by(Run.id)).first()
    queued = session.scalar(select(func.count()).select_from(Run).where(Run.bench_id == bench.id,
                                                                        Run.status == "queued")) or 0
    online = fresh(bench.heartbeat_at, stale_after_s)
    return {"name": bench.name, "devices": devices, "worker": bench.worker if online else None,
            "online": online, "heartbeat_at": iso(bench.heartbeat_at),
            "state": (bench.state or {}).get("state") if online else "offline",
            "current_run": ({"id": active.id, "status": active.status, "procedure": active.procedure,
                             "gyro_id": active.gyro_id, "progress_percent": round(100 * active.progress, 2)}
                            if active else None),
            "queued_runs": int(queued), "latitude_deg": cfg.get("latitude_deg")}

"""Runs: queue (with scheduled start), control requests, state, data and live events.

The API never drives hardware: it writes the run row (``queued``) and operator requests
(``run_requests``); the bench's worker does the rest.  A queued run is cancelled here directly
(guarded so a run a worker just claimed is not touched).
"""
from __future__ import annotations

import csv
import io
import json
import time
from typing import Any, Iterator, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import ValidationError
from sqlalchemy import func, select, update

import procedures
from api.auth import Principal, require
from api.deps import get_db, run_or_404, stale_after_s
from api.problems import Problem, problem_codes, summary, validation_errors
from api.schemas import RowId, ID_PATTERN, DataFormat, DataStream, RunCreate
from api.views import TERMINAL, iso, run_detail, run_summary
from bench.config import BenchConfig
from bench.engine import plan_summary
from bench.errors import PlanError
from bench.storage import queries
from bench.storage.db import Database
from bench.storage.models import Bench, Event, ProbeReadingRow, Run, RunRequest, Telemetry, utcnow

router = APIRouter(prefix="/runs", tags=["runs"])
CONTROL_RESPONSES = {200: {"description": "A queued run was cancelled"},
                     202: {"description": "Request recorded; the bench worker applies it at its next tick"}}
MAX_ROWS = 200_000


def _bench_name(session, run: Run) -> str | None:
    return session.scalar(select(Bench.name).where(Bench.id == run.bench_id)) if run.bench_id else None


@router.post("", status_code=201, summary="Queue a run", openapi_extra=problem_codes(404))
def create_run(body: RunCreate, request: Request, response: Response, db: Database = Depends(get_db),
               who: Principal = Depends(require("operator"))) -> dict[str, Any]:
    """Validate the procedure parameters and the plan against the bench's configuration, then queue
    the run for the bench's worker (at ``start_at`` if given)."""
    with db.session() as s:
        bench = s.scalars(select(Bench).where(Bench.name == body.bench)).first()
        if bench is None:
            known = ", ".join(s.scalars(select(Bench.name).order_by(Bench.name))) or "none configured"
            raise Problem(404, "Unknown bench", f"bench {body.bench!r} is not configured; known: {known}")
        config_doc = dict(bench.config or {})
    module = procedures.get(body.procedure)            # the schema allows only known names
    try:
        params = module.Params.model_validate(body.params)
    except ValidationError as exc:
        errors = validation_errors(list(exc.errors()), ("body", "params"))
        raise Problem(422, "Invalid procedure parameters", summary(errors), errors=errors) from None
    try:
        config = BenchConfig.model_validate(config_doc)
        plan = module.build(params)
        estimate = plan_summary(plan, config)
        procedures.check_duration(estimate)
    except PlanError as exc:
        raise Problem(422, "Plan refused", f"{body.procedure} on bench {body.bench}: {exc}") from None
    units, gyro_id = None, body.gyro_id
    if not config.multi and body.gyro_ids is not None and len(body.gyro_ids) == 1 and "=" not in body.gyro_ids[0]:
        gyro_id = body.gyro_ids[0]             # one gyro on a one-gyro bench: the simple case
    elif body.gyro_ids is not None or config.multi:
        try:
            units = config.assign_gyros(body.gyro_ids if body.gyro_ids is not None else [body.gyro_id])
        except (ValueError, KeyError) as exc:
            raise Problem(422, "Gyros refused", f"bench {body.bench}: {str(exc).strip(chr(39) + chr(34))}") from None
    with db.session() as s:
        run = queries.create_run(s, procedure=body.procedure, parameters=params.model_dump(mode="json"),
                                 config_snapshot=config_doc, operator=body.operator or who.name,
                                 gyro_id=None if units else gyro_id, bench_name=body.bench,
                                 start_at=body.start_at, units=units)
        run.live = {"summary": estimate}
        queries.add_event(s, run.id, "queued", f"run queued by {who.name} on bench {body.bench}"
                          + (f", scheduled for {iso(body.start_at)}" if body.start_at else ""))
        s.flush()
        doc = run_summary(run, body.bench, stale_after_s(request))
    doc["estimated_total_bench_s"] = estimate.get("total_bench_s")
    response.headers["Location"] = f"/runs/{doc['id']}"
    return doc


@router.get("", summary="List runs")
def list_runs(request: Request, db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
              status: list[Literal["queued", "running", "paused", "stopping", "suspended", "completed", "aborted",
                                   "failed"]] | None = Query(None, description="filter: one or more statuses"),
              bench: str | None = Query(None, pattern=ID_PATTERN), gyro_id: str | None = Query(None, pattern=ID_PATTERN),
              procedure: str | None = Query(None, max_length=64),
              limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=10_000_000)) -> dict[str, Any]:
    with db.session() as s:
        stmt = select(Run, Bench.name).outerjoin(Bench, Bench.id == Run.bench_id)
        if status:
            stmt = stmt.where(Run.status.in_(status))
        if bench:
            stmt = stmt.where(Bench.name == bench)
        if gyro_id:
            stmt = stmt.where(Run.gyro_id == gyro_id)
        if procedure:
            stmt = stmt.where(Run.procedure == procedure)
        total = s.scalar(select(func.count()).select_from(stmt.subquery()))
        rows = s.execute(stmt.order_by(Run.id.desc()).limit(limit).offset(offset)).all()
        return {"total": total, "runs": [run_summary(r, name, stale_after_s(request)) for r, name in rows]}


@router.get("/{run_id}", summary="Run state: status, step, progress, ETA, latest readings, gaps, suspensions")
def get_run(run_id: RowId, request: Request, db: Database = Depends(get_db),
            _: Principal = Depends(require("viewer"))) -> dict[str, Any]:
    with db.session() as s:
        run = run_or_404(s, run_id)
        return run_detail(s, db, run, _bench_name(s, run), stale_after_s(request))


def _request(db: Database, run_id: int, command: str, who: Principal) -> JSONResponse:
    with db.session() as s:
        run = run_or_404(s, run_id)
        if run.status == "queued" and command in ("stop", "abort"):
            done = s.execute(update(Run).where(Run.id == run_id, Run.status == "queued")
                             .values(status="aborted", finished_at=utcnow(),
                                     error=f"cancelled before it started ({command} by {who.name})")).rowcount
            if done == 1:
                queries.add_event(s, run_id, "cancelled", f"queued run cancelled by {who.name}")
                return JSONResponse({"run_id": run_id, "status": "aborted", "cancelled": True}, status_code=200)
            s.refresh(run)
        allowed = {"stop": ("running", "paused", "stopping", "suspended"),
                   "abort": ("running", "paused", "stopping", "suspended"),
                   "pause": ("running", "suspended"), "resume": ("paused",)}[command]
        if run.status not in allowed:
            raise Problem(409, "Not possible now", f"run {run_id} is {run.status}; {command} needs a run that is "
                          f"{' or '.join(allowed)}")
        req = RunRequest(run_id=run_id, command=command, requested_by=who.name, created_at=utcnow())
        s.add(req)
        s.flush()
        queries.add_event(s, run_id, f"request_{command}", f"{command} requested by {who.name}")
        return JSONResponse({"run_id": run_id, "request_id": req.id, "command": command, "status": run.status,
                             "detail": "the bench worker applies the request at its next tick"}, status_code=202)


_CONTROL_SUMMARIES = {
    "stop": "Stop: finish the current recording, then safe state (cancels a queued run)",
    "abort": "Abort: safe state now (cancels a queued run)",
    "pause": "Pause a running run (its step clock stops)",
    "resume": "Resume a paused run",
}


def _control_route(command: str):
    def control(run_id: RowId, db: Database = Depends(get_db), who: Principal = Depends(require("operator"))):
        return _request(db, run_id, command, who)

    control.__name__ = f"{command}_run"
    return control


for _command, _summary in _CONTROL_SUMMARIES.items():
    router.add_api_route(f"/{{run_id}}/{_command}", _control_route(_command), methods=["POST"], summary=_summary,
                         name=f"{_command}_run", openapi_extra=problem_codes(409), responses=CONTROL_RESPONSES)


# ------------------------------------------------------------------------------------------ data
def _columns(db: Database, run_id: int, stream: str, t_from: float | None, t_to: float | None) -> dict[str, np.ndarray]:
    if stream in ("seconds", "frames"):
        from bench.storage.export import export_columns
        cols = export_columns(db, run_id, resolution="second" if stream == "seconds" else "frame",
                              t_from=t_from, t_to=t_to)
        return cols
    if stream == "probes":
        p = ProbeReadingRow
        stmt = select(p.t, p.name, p.serial, p.celsius, p.fault).where(p.run_id == run_id)
        names = ("t", "name", "serial", "celsius", "fault")
        order = (p.t, p.name)
        tcol = p.t
    else:
        tm = Telemetry
        names = ("t", "device", "chamber_pv", "chamber_sp", "chamber_ramp_sp", "chamber_mode", "chamber_alarm",
                 "axis1_pos", "axis1_rate", "axis2_pos", "axis2_rate", "psu_volts", "psu_amps", "psu_on")
        stmt = select(*[getattr(tm, n) for n in names]).where(tm.run_id == run_id)
        order = (tm.t, tm.device)
        tcol = tm.t
    if t_from is not None:
        stmt = stmt.where(tcol >= t_from)
    if t_to is not None:
        stmt = stmt.where(tcol <= t_to)
    with db.engine.connect() as conn:
        rows = conn.execute(stmt.order_by(*order).limit(MAX_ROWS * 50 + 1)).all()
    return {n: np.array([r[i] for r in rows], dtype=object) for i, n in enumerate(names)}


def _cell(v: Any) -> Any:
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if np.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.str_):
        return str(v)
    return v


@router.get("/{run_id}/data", summary="Recorded data: 1-s means, frames, probes or telemetry (JSON or CSV)",
            responses={200: {"content": {"application/json": {}, "text/csv": {}}}},
            openapi_extra=problem_codes(413))
def run_data(run_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
             stream: DataStream = Query("seconds", description="seconds = aligned 1-s means (gyro deg/h, probes, "
                                        "chamber...); frames = every gyro frame; probes; telemetry"),
             t_from: float | None = Query(None, description="bench time (s) from, as in the bench_time_s / t column"),
             t_to: float | None = Query(None, description="bench time (s) to"),
             every: int = Query(1, ge=1, le=1_000_000, description="decimation: keep every n-th row"),
             format: DataFormat = Query("json")):
    if t_from is not None and t_to is not None and t_to < t_from:
        raise Problem(422, "Invalid input", f"t_to ({t_to}) is before t_from ({t_from})")
    for name, v in (("t_from", t_from), ("t_to", t_to)):
        if v is not None and not np.isfinite(v):
            raise Problem(422, "Invalid input", f"{name} must be a finite number of seconds")
    with db.session() as s:
        run_or_404(s, run_id)
    cols = _columns(db, run_id, stream, t_from, t_to)
    n = len(next(iter(cols.values()))) if cols else 0
    idx = np.arange(0, n, every)
    if len(idx) > MAX_ROWS:
        raise Problem(413, "Too much data", f"{len(idx)} rows selected (limit {MAX_ROWS}); narrow t_from/t_to or "
                      f"raise 'every' (decimation)")
    names = list(cols)
    if format == "json":
        body = {"run_id": run_id, "stream": stream, "rows": int(len(idx)), "every": every,
                "columns": {k: [_cell(v) for v in cols[k][idx]] for k in names}}
        return JSONResponse(body)

    def lines() -> Iterator[str]:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(names)
        for start in range(0, len(idx), 5000):
            part = idx[start:start + 5000]
            for i in part:
                w.writerow(["" if (c := _cell(cols[k][i])) is None else c for k in names])
            yield buf.getvalue()
            buf.seek(0)
            buf.truncate()
        if not len(idx):
            yield buf.getvalue()

    return StreamingResponse(lines(), media_type="text/csv",
                             headers={"Content-Disposition": f'attachment; filename="run{run_id}-{stream}.csv"'})


# ---------------------------------------------------------------------------------------- events
def _event_doc(e: Event) -> dict[str, Any]:
    return {"id": e.id, "t_bench": e.t_bench, "time": iso(e.wall_time), "kind": e.kind, "message": e.message,
            "level": (e.data or {}).get("level", "info"), "data": e.data}


@router.get("/{run_id}/events", summary="Run events; live as Server-Sent Events with follow=true",
            responses={200: {"content": {"application/json": {}, "text/event-stream": {}}}})
def run_events(run_id: RowId, request: Request, db: Database = Depends(get_db),
               _: Principal = Depends(require("viewer")),
               after: int = Query(0, ge=0, le=2**62, description="only events with a larger id"),
               follow: bool = Query(False, description="stream new events (text/event-stream) until the run ends"),
               limit: int = Query(1000, ge=1, le=10_000),
               max_wait_s: float = Query(3600.0, gt=0, le=86_400, description="end the stream after this many "
                                                                                "seconds")):
    with db.session() as s:
        run_or_404(s, run_id)
    wants_stream = follow or "text/event-stream" in request.headers.get("accept", "")
    if not wants_stream:
        with db.session() as s:
            return {"run_id": run_id, "events": [_event_doc(e) for e in queries.list_events(s, run_id, after_id=after,
                                                                                               limit=limit)]}
    poll_s = float(request.app.state.sse_poll_s)

    def stream() -> Iterator[str]:
        last, last_state, deadline = after, None, time.monotonic() + max_wait_s
        yield "retry: 2000\n\n"
        while True:
            with db.session() as s:
                events = queries.list_events(s, run_id, after_id=last, limit=500)
                run = s.get(Run, run_id)
                state = None if run is None else {"status": run.status, "progress_percent": round(100 * run.progress, 2),
                                                  "step_index": run.current_step,
                                                  "eta_utc": (run.live or {}).get("eta_utc")}
            for e in events:
                last = e.id
                yield f"id: {e.id}\nevent: {e.kind}\ndata: {json.dumps(_event_doc(e))}\n\n"
            if state != last_state:
                last_state = state
                yield f"event: status\ndata: {json.dumps({'run_id': run_id, **(state or {})})}\n\n"
            if state is None or (state["status"] in TERMINAL and not events) or time.monotonic() > deadline:
                yield "event: end\ndata: {}\n\n"
                return
            time.sleep(poll_s)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

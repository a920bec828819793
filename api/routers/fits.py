"""Fits and coefficients: fit a model on stored runs, read a gyro's coefficients, accept a version,
and close the loop.  Fits, close-the-loop analyses and report pages are jobs (``bench.jobs``) executed
by workers: this process only enqueues them (202 with the job's URL) and reads their stored results.

A *fit* is one version of one model for one gyro; it has a row per channel.  ``/fits/{id}`` takes
the id of any of those rows and answers with the whole version.
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from typing import Any, Literal

import orjson
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from sqlalchemy import and_, select

from api.auth import Principal, require
from api.coefficients import NoCoefficients, coefficient_rows, coefficients_document, coefficients_etag
from api.deps import get_db
from api.problems import Problem, problem_codes
from api.schemas import ID_PATTERN, CloseLoopCreate, FitCreate, GyroPath, RowId
from api.views import iso
from bench.analysis import fit_results
from bench.errors import BenchError
from bench.jobs import enqueue
from bench.storage import queries
from bench.storage.db import Database
from bench.storage.models import Analysis, Fit, Gyro, Run

router = APIRouter(tags=["fits"])


# ------------------------------------------------------------------------------------ helpers
def _group_doc(rows: list[Fit], *, full: bool = True) -> dict[str, Any]:
    first = rows[0]
    doc: dict[str, Any] = {"id": min(r.id for r in rows), "gyro_id": first.gyro_id, "model": first.model,
                           "version": first.version, "accepted": all(r.accepted for r in rows),
                           "created_at": iso(first.created_at), "run_ids": first.run_ids}
    channels: dict[str, Any] = {}
    for r in sorted(rows, key=lambda r: r.channel):
        entry: dict[str, Any] = {"coefficients": r.coefficients, "units": (r.result or {}).get("units"),
                                 "probe": ((r.result or {}).get("definition") or {}).get("probe")}
        if full:
            res = r.result or {}
            entry.update(definition=res.get("definition"), validity=res.get("validity"), stats=res.get("stats"),
                         target=res.get("target"), metrics=res.get("metrics"))
        channels[r.channel] = entry
    doc["channels"] = channels
    return doc


def _group_rows(session, fit_id: int) -> list[Fit]:
    one = session.get(Fit, fit_id)
    if one is None:
        raise Problem(404, "Fit not found", f"fit {fit_id} does not exist")
    return list(session.scalars(select(Fit).where(Fit.gyro_id == one.gyro_id, Fit.model == one.model,
                                                  Fit.version == one.version).order_by(Fit.channel)))


# ------------------------------------------------------------------------------ coefficients
@router.get("/gyros/{gyro_id}/coefficients", summary="A gyro's coefficients: the latest accepted fit per model",
            responses={304: {"description": "unchanged since the ETag given in If-None-Match"}})
async def coefficients(gyro_id: GyroPath, request: Request, db: Database = Depends(get_db),
                 _: Principal = Depends(require("viewer")),
                 model: str | None = Query(None, min_length=1, max_length=300),
                 version: int | None = Query(None, ge=1, le=1_000_000,
                                             description="a specific version (of model, or of every model "
                                                         "that has it); accepted or not")):
    if not _valid_id(gyro_id):
        raise Problem(422, "Invalid input", f"gyro id {gyro_id!r}: use 1-64 letters, digits, '.', '_' or '-'")
    try:
        # one indexed query of about a millisecond: run on the event loop (no thread hop); JSON decoded and
        # encoded with orjson; a client holding the same fit rows (If-None-Match) gets 304 without a body
        rows = coefficient_rows(db, gyro_id, model=model, version=version)
        etag = coefficients_etag(rows)
        headers = {"ETag": etag, "Cache-Control": "no-cache"}
        if etag in {t.strip() for t in request.headers.get("if-none-match", "").split(",")}:
            return Response(status_code=304, headers=headers)
        return Response(orjson.dumps(coefficients_document(gyro_id, rows)), media_type="application/json",
                        headers=headers)
    except ValueError as exc:
        raise Problem(422, "Invalid input", str(exc)) from None
    except NoCoefficients as exc:
        raise Problem(404, "No coefficients" if exc.gyro_known else "Gyro not found", str(exc)) from None


@router.get("/gyros/{gyro_id}/coefficients/export",
            summary="One model's coefficients for firmware: json, PX4 or ArduPilot parameters, or a C header",
            responses={200: {"content": {"text/plain": {}, "text/x-c": {}, "application/json": {}}},
                       422: {"description": "the model cannot be expressed in that format (reason given)"}})
def export_coefficients(gyro_id: GyroPath, db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
                        model: str = Query(..., min_length=1, max_length=300),
                        format: Literal["json", "px4", "ardupilot", "c-header"] = Query(...),
                        version: int | None = Query(None, ge=1, le=1_000_000),
                        px4_instance: int = Query(0, ge=0, le=3, description="PX4 gyro instance (TC_G<i>_)"),
                        px4_device_id: int = Query(0, ge=-2**31, le=2**31 - 1, description="PX4 TC_G<i>_ID"),
                        ardupilot_imu: int = Query(1, ge=1, le=3, description="ArduPilot IMU number (INS_TCAL<n>_)"),
                        ardupilot_caltemp_c: float | None = Query(None, ge=-100, le=200,
                                                                  description="temperature of the gyro offsets")):
    from api.coefficients import export_coefficients as export
    from bench.fit.firmware import NotExpressible

    options = {"px4_instance": px4_instance, "px4_device_id": px4_device_id, "ardupilot_imu": ardupilot_imu,
               "ardupilot_caltemp_c": ardupilot_caltemp_c}
    try:
        text, media, suffix = export(db, gyro_id, model, format, version=version, options=options)
    except NotExpressible as exc:
        raise Problem(422, "Not expressible in this format", str(exc)) from None
    except NoCoefficients as exc:
        raise Problem(404, "No coefficients" if exc.gyro_known else "Gyro not found", str(exc)) from None
    return Response(text, media_type=media,
                    headers={"Content-Disposition": f'attachment; filename="{gyro_id}.{_safe_name(model)}{suffix}"'})


def _valid_id(text: str) -> bool:
    import re
    return re.match(ID_PATTERN, text) is not None


@router.get("/gyros/{gyro_id}/fits", summary="Every fit version of a gyro")
def gyro_fits(gyro_id: GyroPath, db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
              model: str | None = Query(None, min_length=1, max_length=300)):
    with db.session() as s:
        if s.get(Gyro, gyro_id) is None:
            raise Problem(404, "Gyro not found", f"no gyro {gyro_id!r} is stored")
        rows = queries.list_fits(s, gyro_id, model=model)
        groups: dict[tuple[str, int], list[Fit]] = {}
        for r in rows:
            groups.setdefault((r.model, r.version), []).append(r)
        return {"gyro_id": gyro_id, "fits": [_group_doc(g, full=False) for g in groups.values()]}


# ------------------------------------------------------------------------------------ listings
@dataclass(frozen=True)
class ListFilters:
    """The filters of the listings: gyro, model, a day range (UTC, both days included) and a limit."""

    gyro_id: str | None
    model: str | None
    lo: dt.datetime | None          # from 00:00 UTC of ``date_from``
    hi: dt.datetime | None          # to 00:00 UTC of the day after ``date_to`` (excluded)
    limit: int


def list_filters(gyro_id: str | None = Query(None, min_length=1, max_length=64),
                 model: str | None = Query(None, min_length=1, max_length=300),
                 date_from: dt.date | None = Query(None, description="on or after this day (UTC)"),
                 date_to: dt.date | None = Query(None, description="on or before this day (UTC)"),
                 limit: int = Query(100, ge=1, le=1000)) -> ListFilters:
    lo = dt.datetime.combine(date_from, dt.time(), dt.timezone.utc) if date_from else None
    hi = dt.datetime.combine(date_to + dt.timedelta(days=1), dt.time(), dt.timezone.utc) if date_to else None
    return ListFilters(gyro_id, model, lo, hi, limit)


def _filtered(stmt, f: ListFilters, gyro_col, created_col):
    if f.gyro_id is not None:
        stmt = stmt.where(gyro_col == f.gyro_id)
    if f.lo is not None:
        stmt = stmt.where(created_col >= f.lo)
    if f.hi is not None:
        stmt = stmt.where(created_col < f.hi)
    return stmt


def _metric(row: Fit, part: str, name: str) -> float | None:
    value = (((row.result or {}).get("metrics") or {}).get(part) or {}).get(name)
    return value if isinstance(value, (int, float)) else None


@router.get("/fits", summary="Stored fit versions, newest first, filtered by gyro, model and creation date")
def list_fits(db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
              f: ListFilters = Depends(list_filters)):
    """One entry per version (gyro, model, version) with its channels' training and validation errors."""
    stmt = _filtered(select(Fit), f, Fit.gyro_id, Fit.created_at)
    if f.model is not None:
        stmt = stmt.where(Fit.model == f.model)
    with db.session() as s:
        groups: dict[tuple[str, str, int], list[Fit]] = {}
        for r in s.scalars(stmt.order_by(Fit.created_at.desc(), Fit.id.desc())):
            key = (r.gyro_id, r.model, r.version)
            if key not in groups and len(groups) >= f.limit:
                break
            groups.setdefault(key, []).append(r)
        out = []
        for rows in groups.values():
            doc = _group_doc(rows, full=False)
            doc["validation_run_ids"] = (rows[0].result or {}).get("validation_run_ids") or []
            for r in rows:
                doc["channels"][r.channel].update(
                    train_rms_dph=_metric(r, "train", "rms_dph"), train_std100_dph=_metric(r, "train", "std100_dph"),
                    validation_rms_dph=_metric(r, "validation", "rms_dph"),
                    validation_std100_dph=_metric(r, "validation", "std100_dph"))
            out.append(doc)
    return {"fits": out}


def _analysis_summary(a: Analysis) -> dict[str, Any]:
    """An analysis without its full result: per channel the verdict, the effects added and the
    validation std of 100-s means before and after."""
    doc = {k: v for k, v in _job_doc(a).items() if k != "result"}
    doc["model"] = (a.request or {}).get("model")
    channels = {}
    for ch, r in ((a.result or {}).get("channels") or {}).items():
        channels[ch] = {"verdict": r.get("verdict"), "effects_added": [e.get("kind") for e in r.get("effects_added") or []],
                        "before_validation_std100_dph": (r.get("before") or {}).get("validation_std100_dph"),
                        "after_validation_std100_dph": (r.get("after") or {}).get("validation_std100_dph"),
                        "noise_floor_dph": r.get("noise_floor_dph")}
    doc["channels"] = channels
    return doc


@router.get("/close-loop", summary="Close-the-loop analyses, newest first, filtered by gyro, model and date")
def list_close_loop(db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
                    f: ListFilters = Depends(list_filters)):
    stmt = _filtered(select(Analysis).where(Analysis.kind == "close_loop"), f, Analysis.gyro_id, Analysis.created_at)
    with db.session() as s:
        rows = [a for a in s.scalars(stmt.order_by(Analysis.created_at.desc(), Analysis.id.desc()))
                if f.model is None or (a.request or {}).get("model") == f.model][:f.limit]
        return {"analyses": [_analysis_summary(a) for a in rows]}


# -------------------------------------------------------------------------------------- fits
@router.post("/fits", status_code=202, summary="Fit a model on stored runs (a job: 202 with the job's URL)",
             openapi_extra=problem_codes(404, 409))
def create_fit(body: FitCreate, db: Database = Depends(get_db), who: Principal = Depends(require("operator"))):
    """Queue a job that fits ``model`` per channel on the recorded data of ``run_ids`` (evaluated on
    ``validation_run_ids`` too), stores it as the next version of the model for the gyro and renders its
    report.  Poll ``GET /jobs/{id}``: once ``done`` its ``result`` names the fit (``fit_id``)."""
    if body.accept and not who.allows("admin"):
        raise Problem(403, "Not allowed", "accepting a fit as the gyro's coefficients needs the admin role")
    overlap = set(body.run_ids) & set(body.validation_run_ids)
    if overlap:
        raise Problem(422, "Invalid input", f"runs {sorted(overlap)} are both training and validation runs")
    _check_model(body.model)
    with db.session() as s:
        gyros = _gyros_of(s, [*body.run_ids, *body.validation_run_ids])
        if len(gyros) > 1:
            raise Problem(409, "Runs of different gyros", f"runs {body.run_ids + body.validation_run_ids} belong "
                          f"to gyros {sorted(map(str, gyros))}")
        job = enqueue(s, "fit", body.model_dump(mode="json"), requested_by=who.name,
                      gyro_id=body.gyro_id or next(iter(gyros), None))
        doc = _job_doc(job)
    return _accepted(doc)


def _check_model(model: str) -> None:
    """Refuse at once a model that is neither a named model nor a formula that parses."""
    from bench.fit.catalog import NAMED_MODELS
    from bench.fit.formula import parse_formula

    if model in NAMED_MODELS:
        return
    try:
        parse_formula(model)
    except BenchError as exc:
        raise Problem(422, "Invalid input", f"model {model!r} is not one of {list(NAMED_MODELS)} and not a "
                      f"formula: {exc}") from None


def _gyros_of(session, run_ids: list[int]) -> set[str | None]:
    gyros = set()
    for rid in run_ids:
        run = session.get(Run, rid)
        if run is None:
            raise Problem(404, "Unknown run", f"run {rid} does not exist")
        gyros.add(run.gyro_id)
    return gyros


def _job_url(job: Analysis | dict[str, Any]) -> str:
    kind, job_id = (job.kind, job.id) if isinstance(job, Analysis) else (job["kind"], job["id"])
    return f"/close-loop/{job_id}" if kind == "close_loop" else f"/jobs/{job_id}"


def _job_doc(a: Analysis) -> dict[str, Any]:
    doc = {"id": a.id, "kind": a.kind, "status": a.status, "url": _job_url(a), "gyro_id": a.gyro_id,
           "request": a.request, "requested_by": a.requested_by, "created_at": iso(a.created_at),
           "started_at": iso(a.started_at), "finished_at": iso(a.finished_at), "attempts": a.attempts,
           "worker": a.worker, "error": a.error, "result": a.result, "fit_id": a.fit_id}
    if a.status == "done" and a.report_html is not None:
        doc["report_url"] = (f"/close-loop/{a.id}/report" if a.kind == "close_loop"
                             else f"/fits/{a.fit_id}/report")
    return doc


def _accepted(doc: dict[str, Any]) -> JSONResponse:
    return JSONResponse(doc, status_code=202, headers={"Location": doc["url"]})


@router.get("/jobs/{job_id}", summary="An analysis job (fit, close-the-loop, report): status and result")
def get_job(job_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    with db.session() as s:
        a = s.get(Analysis, job_id)
        if a is None:
            raise Problem(404, "Not found", f"job {job_id} does not exist")
        return _job_doc(a)


@router.get("/fits/{fit_id}", summary="One fit version (all its channels)")
def get_fit(fit_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    with db.session() as s:
        return _group_doc(_group_rows(s, fit_id))


@router.post("/fits/{fit_id}/accept", summary="Make this version the gyro's accepted coefficients for its model")
def accept_fit(fit_id: RowId, db: Database = Depends(get_db), who: Principal = Depends(require("admin"))):
    with db.session() as s:
        rows = _group_rows(s, fit_id)
        queries.accept_fits(s, rows[0].gyro_id, rows[0].model, rows[0].version)
    with db.session() as s:
        doc = _group_doc(_group_rows(s, fit_id))
    doc["accepted_by"] = who.name
    return doc


@router.get("/fits/{fit_id}/export", summary="Firmware export document (gyrobench.fit.export) of this version",
            openapi_extra=problem_codes(409))
def export_fit(fit_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    from bench.fit.export import build_export

    with db.session() as s:
        rows = _group_rows(s, fit_id)
        gyro = s.get(Gyro, rows[0].gyro_id)
        gyro_type = gyro.type if gyro is not None and gyro.type else None
    try:
        return build_export(rows[0].gyro_id, fit_results(rows), gyro_type=gyro_type,
                            source={"fit_id": fit_id, "run_ids": rows[0].run_ids, "version": rows[0].version})
    except BenchError as exc:
        raise Problem(409, "Cannot export", str(exc)) from None


@router.get("/fits/{fit_id}/report", summary="HTML report of this version on its training / validation runs",
            response_class=HTMLResponse, openapi_extra=problem_codes(409),
            responses={202: {"description": "not rendered yet: the rendering job (its URL) is queued or running"}})
def fit_report(fit_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    """The page rendered once by the fit's job.  A fit stored without one (by a run's Fit step) gets a
    rendering job on the first request: 202 with the job's URL until it is done."""
    with db.session() as s:
        group_id = min(r.id for r in _group_rows(s, fit_id))
        page = s.scalar(select(Analysis.report_html).where(Analysis.fit_id == group_id, Analysis.status == "done",
                                                           Analysis.report_html.is_not(None))
                        .order_by(Analysis.id.desc()).limit(1))
        if page is not None:
            return HTMLResponse(page)
        pending = s.scalars(select(Analysis).where(Analysis.fit_id == group_id, Analysis.kind == "fit_report")
                            .order_by(Analysis.id.desc()).limit(1)).first()
        if pending is not None and pending.status == "failed":
            raise Problem(409, "Cannot render the report", pending.error or "the rendering job failed")
        if pending is None:
            pending = enqueue(s, "fit_report", {"fit_id": group_id}, requested_by="report", fit_id=group_id)
        return _accepted(_job_doc(pending))


# -------------------------------------------------------------------------------- close loop
@router.post("/close-loop", status_code=202,
             summary="Close the loop on a training and a held-out run (a job: 202 with its URL)",
             openapi_extra=problem_codes(404, 409))
def create_close_loop(body: CloseLoopCreate, db: Database = Depends(get_db),
                      who: Principal = Depends(require("operator"))):
    if body.train_run_id == body.validation_run_id:
        raise Problem(409, "Same run twice", "the validation run must be another run than the training run (a "
                      "held-out run)")
    _check_model(body.model)
    with db.session() as s:
        gyros = _gyros_of(s, [body.train_run_id, body.validation_run_id])
        job = enqueue(s, "close_loop", body.model_dump(mode="json"), requested_by=who.name,
                      gyro_id=next(iter(gyros)) if len(gyros) == 1 else None)
        doc = _job_doc(job)
    return _accepted(doc)


@router.get("/close-loop/{analysis_id}", summary="Close-the-loop analysis: status and report")
def get_close_loop(analysis_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    with db.session() as s:
        a = s.scalars(select(Analysis).where(and_(Analysis.id == analysis_id, Analysis.kind == "close_loop"))).first()
        if a is None:
            raise Problem(404, "Not found", f"close-loop analysis {analysis_id} does not exist")
        return _job_doc(a)


@router.get("/close-loop/{analysis_id}/report", response_class=HTMLResponse,
            summary="Close-the-loop report page: residual before/after vs time, T, dT/dt; Allan deviation",
            openapi_extra=problem_codes(409))
def close_loop_report(analysis_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    with db.session() as s:
        a = s.scalars(select(Analysis).where(and_(Analysis.id == analysis_id, Analysis.kind == "close_loop"))).first()
        if a is None:
            raise Problem(404, "Not found", f"close-loop analysis {analysis_id} does not exist")
        if a.status != "done":
            raise Problem(409, "Not ready", f"close-loop analysis {analysis_id} is {a.status}; the report exists once "
                                            "it is done")
        if a.report_html is None:
            raise Problem(404, "No report", f"close-loop analysis {analysis_id} has no stored report")
        return HTMLResponse(a.report_html)


def _safe_name(text: str) -> str:
    import re
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)[:64]

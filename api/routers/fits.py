"""Fits and coefficients: fit a model on stored runs, read a gyro's coefficients, accept a version,
and close the loop (long: runs in the background, polled by id).

A *fit* is one version of one model for one gyro; it has a row per channel.  ``/fits/{id}`` takes
the id of any of those rows and answers with the whole version.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import threading
from typing import Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from sqlalchemy import and_, func, select

from api.auth import Principal, require
from api.coefficients import NoCoefficients, load_coefficients
from api.deps import get_db
from api.problems import Problem, problem_codes
from api.schemas import ID_PATTERN, GyroPath, RowId, CloseLoopCreate, FitCreate
from api.views import iso
from bench.errors import BenchError
from bench.fit.base import Dataset, FitResult, channel_probe_map
from bench.storage import queries
from bench.storage.db import Database
from bench.storage.models import Analysis, Fit, Gyro, Run, utcnow

router = APIRouter(tags=["fits"])
RUN_GAP_S = 86_400.0       # time offset between concatenated runs (rate filters see a gap, not a jump)
_FIT_FIELDS = [f.name for f in dataclasses.fields(FitResult)]


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


def _results(rows: list[Fit]) -> list[FitResult]:
    out = []
    for r in rows:
        res = r.result or {}
        out.append(FitResult(**{k: res[k] for k in _FIT_FIELDS if k in res}))
    return out


def load_runs_dataset(db: Database, run_ids: list[int], latitude_deg: float | None) -> tuple[Dataset, str | None]:
    """The recorded data of ``run_ids`` as one Dataset (runs one after the other, RUN_GAP_S apart) and their
    common gyro id.  Refuses unknown runs, runs of different gyros and runs with too little data."""
    from bench.storage.export import run_dataset

    gyro_ids, parts = set(), []
    with db.session() as s:
        for rid in run_ids:
            run = s.get(Run, rid)
            if run is None:
                raise Problem(404, "Unknown run", f"run {rid} does not exist")
            gyro_ids.add(run.gyro_id)
            parts.append((rid, latitude_deg))
    if len(gyro_ids) > 1:
        raise Problem(409, "Runs of different gyros", f"runs {run_ids} belong to gyros {sorted(map(str, gyro_ids))}")
    datasets = []
    for rid, lat in parts:
        ds = run_dataset(rid, db, latitude_deg=lat)
        if "temp_point_c" in ds.columns:       # segment label (set point), not a probe: never a fit input
            ds = Dataset({k: v for k, v in ds.columns.items() if k != "temp_point_c"}, ds.meta)
        if len(ds) < 10:
            raise Problem(409, "Not enough data", f"run {rid} has {len(ds)} recorded seconds stored; at least 10 "
                          f"are needed to fit")
        datasets.append(ds)
    if len(datasets) == 1:
        return datasets[0], gyro_ids.pop()
    common = [k for k in datasets[0].columns if all(k in d.columns for d in datasets[1:])]
    offset, merged = 0.0, {k: [] for k in common}
    for d in datasets:
        for k in common:
            merged[k].append(d.columns[k] + offset if k == "time_s" else d.columns[k])
        offset += float(d.columns["time_s"][-1]) + RUN_GAP_S
    meta = dict(datasets[0].meta)
    meta["run_id"] = ",".join(str(r) for r in run_ids)
    maps = {rid: channel_probe_map(d) for rid, d in zip(run_ids, datasets)}
    merged_map: dict[str, str] = {}
    for rid, mapping in maps.items():
        for ch, probe in mapping.items():
            if merged_map.setdefault(ch, probe) != probe:
                raise Problem(422, "Runs disagree on channel probes",
                              f"channel {ch}: probe {probe} in run {rid}, {merged_map[ch]} in an earlier run of "
                              f"{run_ids}")
    if merged_map:
        meta["channel_probes"] = merged_map
    if any("latitude_deg" not in d.meta for d in datasets):
        meta.pop("latitude_deg", None)
    return Dataset({k: np.concatenate(v) for k, v in merged.items()}, meta), gyro_ids.pop()


# ------------------------------------------------------------------------------ coefficients
@router.get("/gyros/{gyro_id}/coefficients", summary="A gyro's coefficients: the latest accepted fit per model")
async def coefficients(gyro_id: GyroPath, request: Request, db: Database = Depends(get_db),
                 _: Principal = Depends(require("viewer")),
                 model: str | None = Query(None, min_length=1, max_length=300),
                 version: int | None = Query(None, ge=1, le=1_000_000,
                                             description="a specific version (of model, or of every model "
                                                         "that has it); accepted or not")):
    if not _valid_id(gyro_id):
        raise Problem(422, "Invalid input", f"gyro id {gyro_id!r}: use 1-64 letters, digits, '.', '_' or '-'")
    try:
        # one indexed query of about a millisecond: run on the event loop (no thread hop); the stored JSON
        # documents are answered as they are, without re-encoding them field by field
        return JSONResponse(load_coefficients(db, gyro_id, model=model, version=version))
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
def _day_bounds(date_from: dt.date | None, date_to: dt.date | None) -> tuple[dt.datetime | None, dt.datetime | None]:
    """[from 00:00 UTC, the day after ``date_to`` 00:00 UTC): both days included."""
    lo = dt.datetime.combine(date_from, dt.time(), dt.timezone.utc) if date_from else None
    hi = dt.datetime.combine(date_to + dt.timedelta(days=1), dt.time(), dt.timezone.utc) if date_to else None
    return lo, hi


def _metric(row: Fit, part: str, name: str) -> float | None:
    value = (((row.result or {}).get("metrics") or {}).get(part) or {}).get(name)
    return value if isinstance(value, (int, float)) else None


@router.get("/fits", summary="Stored fit versions, newest first, filtered by gyro, model and creation date")
def list_fits(db: Database = Depends(get_db), _: Principal = Depends(require("viewer")),
              gyro_id: str | None = Query(None, min_length=1, max_length=64),
              model: str | None = Query(None, min_length=1, max_length=300),
              date_from: dt.date | None = Query(None, description="created on or after this day (UTC)"),
              date_to: dt.date | None = Query(None, description="created on or before this day (UTC)"),
              limit: int = Query(100, ge=1, le=1000)):
    """One entry per version (gyro, model, version) with its channels' training and validation errors."""
    lo, hi = _day_bounds(date_from, date_to)
    stmt = select(Fit)
    if gyro_id is not None:
        stmt = stmt.where(Fit.gyro_id == gyro_id)
    if model is not None:
        stmt = stmt.where(Fit.model == model)
    if lo is not None:
        stmt = stmt.where(Fit.created_at >= lo)
    if hi is not None:
        stmt = stmt.where(Fit.created_at < hi)
    with db.session() as s:
        groups: dict[tuple[str, str, int], list[Fit]] = {}
        for r in s.scalars(stmt.order_by(Fit.created_at.desc(), Fit.id.desc())):
            key = (r.gyro_id, r.model, r.version)
            if key not in groups and len(groups) >= limit:
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
    doc = {k: v for k, v in _analysis_doc(a).items() if k != "result"}
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
                    gyro_id: str | None = Query(None, min_length=1, max_length=64),
                    model: str | None = Query(None, min_length=1, max_length=300),
                    date_from: dt.date | None = Query(None, description="requested on or after this day (UTC)"),
                    date_to: dt.date | None = Query(None, description="requested on or before this day (UTC)"),
                    limit: int = Query(100, ge=1, le=1000)):
    lo, hi = _day_bounds(date_from, date_to)
    stmt = select(Analysis).where(Analysis.kind == "close_loop")
    if gyro_id is not None:
        stmt = stmt.where(Analysis.gyro_id == gyro_id)
    if lo is not None:
        stmt = stmt.where(Analysis.created_at >= lo)
    if hi is not None:
        stmt = stmt.where(Analysis.created_at < hi)
    with db.session() as s:
        rows = [a for a in s.scalars(stmt.order_by(Analysis.created_at.desc(), Analysis.id.desc()))
                if model is None or (a.request or {}).get("model") == model][:limit]
        return {"analyses": [_analysis_summary(a) for a in rows]}


# -------------------------------------------------------------------------------------- fits
@router.post("/fits", status_code=201, summary="Fit a model on stored runs",
             openapi_extra=problem_codes(404, 409))
def create_fit(body: FitCreate, db: Database = Depends(get_db), who: Principal = Depends(require("operator"))):
    """Fit ``model`` per channel on the recorded data of ``run_ids`` (evaluated on
    ``validation_run_ids`` too) and store it as the next version of the model for the gyro."""
    from bench.fit.channels import fit_channels

    if body.accept and not who.allows("admin"):
        raise Problem(403, "Not allowed", "accepting a fit as the gyro's coefficients needs the admin role")
    overlap = set(body.run_ids) & set(body.validation_run_ids)
    if overlap:
        raise Problem(422, "Invalid input", f"runs {sorted(overlap)} are both training and validation runs")
    train, gyro_id = load_runs_dataset(db, body.run_ids, body.latitude_deg)
    validate = None
    if body.validation_run_ids:
        validate, vgyro = load_runs_dataset(db, body.validation_run_ids, body.latitude_deg)
        if vgyro != gyro_id:
            raise Problem(409, "Runs of different gyros", f"validation runs belong to gyro {vgyro}, training "
                          f"runs to {gyro_id}")
    gyro_id = body.gyro_id or gyro_id
    if gyro_id is None:
        raise Problem(422, "Invalid input", "the runs have no gyro id; give gyro_id")
    channels = list(body.channels) if body.channels else train.gyro_channels()
    missing = [c for c in channels if f"gyro_{c}" not in train]
    if missing:
        raise Problem(409, "Channel not recorded",
                      f"channels {missing} are not in the data (have {train.gyro_channels()})")
    opts = {"latitude_deg": body.latitude_deg} if body.latitude_deg is not None else {}
    try:
        doc, results = fit_channels(body.model, train, validate, channels, opts)
    except (BenchError, ValueError, KeyError, np.linalg.LinAlgError) as exc:
        raise Problem(409, "Fit failed", f"{body.model} on runs {body.run_ids}: {str(exc).strip(chr(39))}") from None
    stored = []
    for r in results:
        item = r.to_json()
        item["metrics"] = {k: v for k, v in doc["channels"].get(r.channel, {}).items()
                           if k in ("train", "validation")}
        item["validation_run_ids"] = body.validation_run_ids
        stored.append(item)
    with db.session() as s:
        versions = queries.save_fits(s, gyro_id, body.run_ids, stored, accepted=body.accept)
        model_name = results[0].model
        rows = list(s.scalars(select(Fit).where(Fit.gyro_id == gyro_id, Fit.model == model_name,
                                                Fit.version == versions[model_name])))
        out = _group_doc(rows)
    out["requested_by"] = who.name
    return out


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
        return build_export(rows[0].gyro_id, _results(rows), gyro_type=gyro_type,
                            source={"fit_id": fit_id, "run_ids": rows[0].run_ids, "version": rows[0].version})
    except BenchError as exc:
        raise Problem(409, "Cannot export", str(exc)) from None


@router.get("/fits/{fit_id}/report", summary="HTML report of this version on its training / validation runs",
            response_class=HTMLResponse, openapi_extra=problem_codes(409))
def fit_report(fit_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    from bench.fit.catalog import predict
    from bench.fit.report import render_fit_report

    with db.session() as s:
        rows = _group_rows(s, fit_id)
    first = rows[0]
    train, _g = load_runs_dataset(db, [int(r) for r in first.run_ids], None)
    val_ids = (first.result or {}).get("validation_run_ids") or []
    validate = load_runs_dataset(db, [int(r) for r in val_ids], None)[0] if val_ids else None
    try:
        page = render_fit_report(_results(rows), train, validate, predict=predict,
                                 title=f"{first.gyro_id}: {first.model} v{first.version}")
    except (BenchError, ValueError, KeyError) as exc:
        raise Problem(409, "Cannot render the report", f"{type(exc).__name__}: {exc}") from None
    return HTMLResponse(page)


# -------------------------------------------------------------------------------- close loop
def _close_loop_analysis(db: Database, body: dict[str, Any]) -> tuple[dict[str, Any], Dataset, Dataset]:
    """Run the close-the-loop analysis a request describes (deterministic: the report page reruns it
    to draw the residuals, which are not stored)."""
    from bench.fit.closeloop import close_loop

    train, _ = load_runs_dataset(db, [body["train_run_id"]], body.get("latitude_deg"))
    validate, _ = load_runs_dataset(db, [body["validation_run_id"]], body.get("latitude_deg"))
    report = close_loop(train, validate, body["model"], channels=body.get("channels"),
                        latitude_deg=body.get("latitude_deg"))
    return report, train, validate


def _close_loop_job(db: Database, analysis_id: int, body: dict[str, Any]) -> None:
    from bench.fit.closeloop import public
    from bench.jsonsafe import jsonable

    with db.session() as s:
        a = s.get(Analysis, analysis_id)
        a.status = "running"
    try:
        report, _, _ = _close_loop_analysis(db, body)
        result, status, error = jsonable(public(report)), "done", None
    except Problem as exc:
        result, status, error = None, "failed", exc.detail
    except Exception as exc:  # noqa: BLE001 - the failure is the analysis' result, reported to the caller
        result, status, error = None, "failed", f"{type(exc).__name__}: {exc}"
    with db.session() as s:
        a = s.get(Analysis, analysis_id)
        a.status, a.result, a.error, a.finished_at = status, result, error, utcnow()


def _analysis_doc(a: Analysis) -> dict[str, Any]:
    return {"id": a.id, "kind": a.kind, "status": a.status, "gyro_id": a.gyro_id, "request": a.request,
            "requested_by": a.requested_by, "created_at": iso(a.created_at), "finished_at": iso(a.finished_at),
            "error": a.error, "result": a.result}


@router.post("/close-loop", status_code=202, summary="Close the loop on a training and a held-out run (background)",
             openapi_extra=problem_codes(404, 409))
def create_close_loop(body: CloseLoopCreate, request: Request, db: Database = Depends(get_db),
                      who: Principal = Depends(require("operator"))):
    if body.train_run_id == body.validation_run_id:
        raise Problem(409, "Same run twice", "the validation run must be another run than the training run (a "
                      "held-out run)")
    with db.session() as s:
        gyros = set()
        for rid in (body.train_run_id, body.validation_run_id):
            run = s.get(Run, rid)
            if run is None:
                raise Problem(404, "Unknown run", f"run {rid} does not exist")
            gyros.add(run.gyro_id)
        a = Analysis(kind="close_loop", gyro_id=next(iter(gyros)) if len(gyros) == 1 else None,
                     request=body.model_dump(mode="json"), status="queued", requested_by=who.name, created_at=utcnow())
        s.add(a)
        s.flush()
        doc = _analysis_doc(a)
    t = threading.Thread(target=_close_loop_job, args=(db, doc["id"], body.model_dump(mode="json")),
                         name=f"close-loop-{doc['id']}", daemon=True)
    t.start()
    request.app.state.jobs.append(t)
    return doc


@router.get("/close-loop/{analysis_id}", summary="Close-the-loop analysis: status and report")
def get_close_loop(analysis_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    with db.session() as s:
        a = s.scalars(select(Analysis).where(and_(Analysis.id == analysis_id, Analysis.kind == "close_loop"))).first()
        if a is None:
            raise Problem(404, "Not found", f"close-loop analysis {analysis_id} does not exist")
        return _analysis_doc(a)


@router.get("/close-loop/{analysis_id}/report", response_class=HTMLResponse,
            summary="Close-the-loop report page: residual before/after vs time, T, dT/dt; Allan deviation",
            openapi_extra=problem_codes(409))
def close_loop_report(analysis_id: RowId, db: Database = Depends(get_db), _: Principal = Depends(require("viewer"))):
    from bench.fit.closeloop_report import render_close_loop_report

    with db.session() as s:
        a = s.scalars(select(Analysis).where(and_(Analysis.id == analysis_id, Analysis.kind == "close_loop"))).first()
        if a is None:
            raise Problem(404, "Not found", f"close-loop analysis {analysis_id} does not exist")
        if a.status != "done":
            raise Problem(409, "Not ready", f"close-loop analysis {analysis_id} is {a.status}; the report exists once "
                                            "it is done")
        body = dict(a.request)
    try:
        report, train, validate = _close_loop_analysis(db, body)
        page = render_close_loop_report(report, train, validate,
                                        title=f"Close-the-loop {analysis_id}: runs {body['train_run_id']} -> "
                                              f"{body['validation_run_id']}")
    except (BenchError, ValueError, KeyError) as exc:
        raise Problem(409, "Cannot render the report", f"{type(exc).__name__}: {exc}") from None
    return HTMLResponse(page)


def _safe_name(text: str) -> str:
    import re
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)[:64]

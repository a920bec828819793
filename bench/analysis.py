"""The analyses behind the fit and close-the-loop jobs: read stored runs as one Dataset, fit a model per
channel, close the loop, render their report pages.  CPU-heavy: called by the job workers
(``bench.jobs``), never by the API process, which only enqueues and reads.

Each ``*_job`` function takes the job's request document and returns an ``Outcome``: the result
document, the report page, and (fits) the rows to store, which the worker writes in the same
transaction that finishes the job under its lease.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bench.errors import BenchError
from bench.fit.base import Dataset, FitResult, channel_probe_map
from bench.storage.db import Database
from bench.storage.models import Fit, Run

RUN_GAP_S = 86_400.0       # time offset between concatenated runs (rate filters see a gap, not a jump)
_FIT_FIELDS = [f.name for f in dataclasses.fields(FitResult)]


class AnalysisInputError(BenchError):
    """The request cannot be analysed as given (unknown run, runs of different gyros, too little data)."""


@dataclasses.dataclass
class Outcome:
    result: dict[str, Any]
    report_html: str | None = None
    gyro_id: str | None = None
    fits: list[dict[str, Any]] | None = None          # fit rows to store (fit jobs)
    accept: bool = False
    run_ids: list[int] | None = None


def fit_results(rows: list[Fit]) -> list[FitResult]:
    """The FitResults stored in the rows of one fit version."""
    out = []
    for r in rows:
        res = r.result or {}
        out.append(FitResult(**{k: res[k] for k in _FIT_FIELDS if k in res}))
    return out


def load_runs_dataset(db: Database, run_ids: list[int], latitude_deg: float | None) -> tuple[Dataset, str | None]:
    """The recorded data of ``run_ids`` as one Dataset (runs one after the other, RUN_GAP_S apart) and their
    common gyro id.  Refuses unknown runs, runs of different gyros and runs with too little data."""
    from bench.storage.export import run_dataset

    gyro_ids = set()
    with db.session() as s:
        for rid in run_ids:
            run = s.get(Run, rid)
            if run is None:
                raise AnalysisInputError(f"run {rid} does not exist")
            gyro_ids.add(run.gyro_id)
    if len(gyro_ids) > 1:
        raise AnalysisInputError(f"runs {run_ids} belong to gyros {sorted(map(str, gyro_ids))}")
    datasets = []
    for rid in run_ids:
        ds = run_dataset(rid, db, latitude_deg=latitude_deg)
        if "temp_point_c" in ds.columns:       # segment label (set point), not a probe: never a fit input
            ds = Dataset({k: v for k, v in ds.columns.items() if k != "temp_point_c"}, ds.meta)
        if len(ds) < 10:
            raise AnalysisInputError(f"run {rid} has {len(ds)} recorded seconds stored; at least 10 are needed "
                                     f"to fit")
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
    merged_map: dict[str, str] = {}
    for rid, d in zip(run_ids, datasets):
        for ch, probe in channel_probe_map(d).items():
            if merged_map.setdefault(ch, probe) != probe:
                raise AnalysisInputError(f"runs disagree on channel probes: channel {ch}: probe {probe} in run "
                                         f"{rid}, {merged_map[ch]} in an earlier run of {run_ids}")
    if merged_map:
        meta["channel_probes"] = merged_map
    if any("latitude_deg" not in d.meta for d in datasets):
        meta.pop("latitude_deg", None)
    return Dataset({k: np.concatenate(v) for k, v in merged.items()}, meta), gyro_ids.pop()


# ------------------------------------------------------------------------------------------ jobs
def fit_job(db: Database, request: dict[str, Any]) -> Outcome:
    """Fit ``request["model"]`` per channel on the runs, evaluate it on the validation runs, render the
    report; the fit rows are stored by the worker as the model's next version for the gyro."""
    from bench.fit.catalog import predict
    from bench.fit.channels import fit_channels
    from bench.fit.report import render_fit_report

    run_ids = [int(r) for r in request["run_ids"]]
    val_ids = [int(r) for r in request.get("validation_run_ids") or []]
    latitude = request.get("latitude_deg")
    train, gyro_id = load_runs_dataset(db, run_ids, latitude)
    validate = None
    if val_ids:
        validate, vgyro = load_runs_dataset(db, val_ids, latitude)
        if vgyro != gyro_id:
            raise AnalysisInputError(f"validation runs belong to gyro {vgyro}, training runs to {gyro_id}")
    gyro_id = request.get("gyro_id") or gyro_id
    if gyro_id is None:
        raise AnalysisInputError("the runs have no gyro id; give gyro_id")
    channels = list(request.get("channels") or []) or train.gyro_channels()
    missing = [c for c in channels if f"gyro_{c}" not in train]
    if missing:
        raise AnalysisInputError(f"channels {missing} are not in the data (have {train.gyro_channels()})")
    opts = {"latitude_deg": latitude} if latitude is not None else {}
    try:
        doc, results = fit_channels(request["model"], train, validate, channels, opts)
    except (ValueError, KeyError, np.linalg.LinAlgError) as exc:
        raise AnalysisInputError(f"{request['model']} on runs {run_ids}: {str(exc).strip(chr(39))}") from None
    stored = []
    for r in results:
        item = r.to_json()
        item["metrics"] = {k: v for k, v in doc["channels"].get(r.channel, {}).items()
                           if k in ("train", "validation")}
        item["validation_run_ids"] = val_ids
        stored.append(item)
    page = render_fit_report(results, train, validate, predict=predict,
                             title=f"{gyro_id}: {results[0].model} on runs {run_ids}")
    return Outcome(result={"gyro_id": gyro_id, "model": results[0].model, "glitches_removed": doc["glitches_removed"]},
                   report_html=page, gyro_id=gyro_id,
                   fits=stored, accept=bool(request.get("accept")), run_ids=run_ids)


def fit_report_job(db: Database, request: dict[str, Any]) -> Outcome:
    """Render the report page of a stored fit version (a fit stored by a run's Fit step, say)."""
    from sqlalchemy import select

    from bench.fit.catalog import predict
    from bench.fit.report import render_fit_report

    with db.session() as s:
        one = s.get(Fit, int(request["fit_id"]))
        if one is None:
            raise AnalysisInputError(f"fit {request['fit_id']} does not exist")
        rows = list(s.scalars(select(Fit).where(Fit.gyro_id == one.gyro_id, Fit.model == one.model,
                                                Fit.version == one.version).order_by(Fit.channel)))
        s.expunge_all()
    first = rows[0]
    train, _ = load_runs_dataset(db, [int(r) for r in first.run_ids], None)
    val_ids = (first.result or {}).get("validation_run_ids") or []
    validate = load_runs_dataset(db, [int(r) for r in val_ids], None)[0] if val_ids else None
    page = render_fit_report(fit_results(rows), train, validate, predict=predict,
                             title=f"{first.gyro_id}: {first.model} v{first.version}")
    return Outcome(result={"fit_id": min(r.id for r in rows), "gyro_id": first.gyro_id, "model": first.model,
                           "version": first.version}, report_html=page, gyro_id=first.gyro_id)


def close_loop_job(db: Database, request: dict[str, Any]) -> Outcome:
    """Close the loop on a training and a held-out run; the result is ``bench.fit.closeloop.public`` of the
    report, the page is the close-the-loop report."""
    from bench.fit.closeloop import close_loop, public
    from bench.fit.closeloop_report import render_close_loop_report
    from bench.jsonsafe import jsonable

    latitude = request.get("latitude_deg")
    train, gyro_id = load_runs_dataset(db, [int(request["train_run_id"])], latitude)
    validate, _ = load_runs_dataset(db, [int(request["validation_run_id"])], latitude)
    report = close_loop(train, validate, request["model"], channels=request.get("channels"), latitude_deg=latitude)
    page = render_close_loop_report(report, train, validate,
                                    title=f"Close-the-loop: runs {request['train_run_id']} -> "
                                          f"{request['validation_run_id']}")
    return Outcome(result=jsonable(public(report)), report_html=page, gyro_id=gyro_id)


JOBS = {"fit": fit_job, "fit_report": fit_report_job, "close_loop": close_loop_job}

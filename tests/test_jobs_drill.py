"""Durable analysis jobs under faults, on SQLite and PostgreSQL, with real processes: the API
(uvicorn) and analysis workers (``bench worker --analysis``).

Drill: a close-the-loop job is queued over HTTP; the worker that claims it stops at the job hold point
(``BENCH_JOB_HOLD_FILE``: its analysis has run, nothing of it is stored yet), and there it and the API are
killed with SIGKILL.  The hold is lifted, a new API and a new worker come up: the job is claimed again (its
heartbeat is stale), ends ``done`` and its report page is served as stored.  Also: a held worker goes on
when the hold file is removed; a worker frozen past its lease whose job was re-run by another finishes
nothing and stores nothing when it wakes (fenced).  Data are just above the close-loop minimum lengths.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest

from bench.jobs import JobRunner, enqueue
from bench.storage import open_database
from bench.storage.models import Analysis, Fit
from tests import synth
from tests.api_support import OPERATOR, TOKENS_TEXT, VIEWER
from tests.service_support import SAFETY_S, Services, wait_for

HIDDEN = {"gradient": 0.06, "rate": 0.08}


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    return request.getfixturevalue("pg_fresh_url")


def _services(tmp_path: Path, db_url: str) -> Services:
    return Services(tmp_path, BENCH_DATABASE_URL=db_url, BENCH_TOKENS=TOKENS_TEXT)


def _start_worker(services: Services, hold_file: Path):
    return services.worker("--analysis", "--heartbeat", "0.2", "--stale-after", "1.5", "--poll", "0.05",
                           "--log-level", "warning", BENCH_JOB_HOLD_FILE=str(hold_file))


def _job(db, job_id: int) -> Analysis:
    with db.session() as s:
        job = s.get(Analysis, job_id)
        s.expunge(job)
        return job


def _import_pair(db):
    from bench.commands.service import import_dataset

    train, _ = synth.make_run(synth.SHORT_TRAIN_PROFILE, HIDDEN, seed=1, dt=1.0)
    validate, _ = synth.make_run(synth.SHORT_VALIDATE_PROFILE, HIDDEN, seed=2, dt=1.0)
    return import_dataset(db, train, "G-DRILL"), import_dataset(db, validate, "G-DRILL")


def _held(hold_file: Path) -> tuple[int, str] | None:
    """(job id, worker id) a worker wrote once it stopped at the hold point, or None."""
    try:
        job_id, worker = Path(f"{hold_file}.held").read_text().split()
    except FileNotFoundError:
        return None
    return int(job_id), worker


def test_kill_api_and_worker_during_a_close_loop_job(db_url, tmp_path):
    db = open_database(db_url)
    hold = tmp_path / "job.hold"
    hold.touch()
    try:
        with _services(tmp_path, db_url) as services:
            train, val = _import_pair(db)
            worker = _start_worker(services, hold)          # it boots while the API does; nothing is queued yet
            api, base = services.api()
            r = httpx.post(f"{base}/close-loop", json={"model": "static", "train_run_id": train,
                                                       "validation_run_id": val, "channels": ["x"]},
                           headers=OPERATOR, timeout=30)
            assert r.status_code == 202, r.text
            job_id = r.json()["id"]
            held_job, held_by = services.wait_for(lambda: _held(hold), "the worker to reach the job hold point",
                                                  worker, interval=0.01)
            first = _job(db, job_id)
            assert (held_job, held_by) == (job_id, first.worker)
            assert (first.status, first.attempts, first.finished_at, first.result, first.report_html) == \
                ("running", 1, None, None, None), "the job must be running, nothing of it stored, when it is killed"
            services.kill(worker)
            services.kill(api)
            assert _job(db, job_id).status == "running"
            # lift the hold, restart everything: a new API, a new worker; the job is claimed again once its
            # heartbeat is stale
            hold.unlink()
            Path(f"{hold}.held").unlink()
            worker = _start_worker(services, hold)
            _, base = services.api()
            doc = services.wait_for(
                lambda: (d := httpx.get(f"{base}/close-loop/{job_id}", headers=VIEWER, timeout=30).json())
                ["status"] in ("done", "failed") and d, "the job to end", worker, interval=0.2)
            assert doc["status"] == "done", doc["error"]
            assert doc["attempts"] == 2 and doc["worker"] != first.worker
            assert doc["result"]["channels"]["x"]["verdict"]
            assert _held(hold) is None, "the second worker must not have held"
            stored = _job(db, job_id)
            assert (stored.worker, stored.attempts) == (doc["worker"], 2) and stored.report_html
            t0 = time.perf_counter()
            page = httpx.get(f"{base}{doc['report_url']}", headers=VIEWER, timeout=30)
            print(f"\n{db.dialect}: report page ({len(page.content) / 1e6:.1f} MB) served in "
                  f"{(time.perf_counter() - t0) * 1e3:.0f} ms")
            assert page.status_code == 200 and page.text.lstrip().lower().startswith("<!doctype html")
            assert page.text == stored.report_html
    finally:
        db.dispose()


def test_a_worker_that_lost_its_job_stores_nothing(db_url):
    """Worker A claims a fit job and goes silent past its lease; B claims it again and finishes it; when
    A finishes its own computation, the guarded finish finds the job no longer A's: no second fit version,
    the job keeps B's result."""
    from bench.commands.service import import_dataset
    from tests.test_api_http import synthetic_dataset

    db = open_database(db_url)
    try:
        train = import_dataset(db, synthetic_dataset(seed=7), "G-FENCE")
        with db.session() as s:
            job_id = enqueue(s, "fit", {"model": "static", "run_ids": [train]}).id
        a = JobRunner(db, worker_id="worker-a", heartbeat_s=0.05, stale_after_s=0.2)
        b = JobRunner(db, worker_id="worker-b", heartbeat_s=0.05, stale_after_s=0.2)
        assert a.claim()[0] == job_id                       # A holds it, and then stops heartbeating
        wait_for(lambda: b.claim() is not None, SAFETY_S, "the job's lease to go stale", interval=0.01)
        with db.session() as s:                              # B's claim, seen from the database
            assert s.get(Analysis, job_id).worker == "worker-b"
        from bench.analysis import fit_job
        # both compute the same deterministic fit of the same run (its rows to store): computed once
        outcome = fit_job(db, {"model": "static", "run_ids": [train]})
        assert outcome.fits
        assert b._finish(job_id, "done", outcome=outcome) == "done"
        assert a._finish(job_id, "done", outcome=outcome) == "lost"
        with db.session() as s:
            job = s.get(Analysis, job_id)
            assert (job.status, job.worker, job.attempts) == ("done", "worker-b", 2)
            versions = {f.version for f in s.query(Fit).filter(Fit.gyro_id == "G-FENCE")}
        assert versions == {1}
    finally:
        db.dispose()


def test_a_held_job_goes_on_when_the_hold_file_is_removed(tmp_path):
    """At the hold point the job is running under a live heartbeat, nothing stored; removing the file lets
    the same worker finish it."""
    from bench.commands.service import import_dataset
    from tests.test_api_http import synthetic_dataset

    db = open_database(f"sqlite:///{tmp_path / 'hold.sqlite'}")
    hold = tmp_path / "job.hold"
    hold.touch()
    runner = JobRunner(db, worker_id="worker-h", heartbeat_s=0.05, stale_after_s=0.2, hold_file=str(hold))
    try:
        train = import_dataset(db, synthetic_dataset(seed=3), "G-HOLD")
        with db.session() as s:
            job_id = enqueue(s, "fit", {"model": "static", "run_ids": [train]}).id
        thread = threading.Thread(target=runner.run_one)
        thread.start()
        assert wait_for(lambda: _held(hold), SAFETY_S, "the hold point", interval=0.01) == (job_id, "worker-h")
        beat = _job(db, job_id).heartbeat_at
        wait_for(lambda: _job(db, job_id).heartbeat_at > beat, SAFETY_S, "a heartbeat while held", interval=0.01)
        job = _job(db, job_id)
        assert (job.status, job.worker, job.result, job.fit_id) == ("running", "worker-h", None, None)
        hold.unlink()
        thread.join(timeout=SAFETY_S)
        assert not thread.is_alive() and runner.done == [(job_id, "done")]
        with db.session() as s:
            assert s.query(Fit).filter(Fit.gyro_id == "G-HOLD").count() > 0
    finally:
        hold.unlink(missing_ok=True)
        db.dispose()

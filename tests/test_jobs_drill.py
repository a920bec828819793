"""Durable analysis jobs under faults, on SQLite and PostgreSQL, with real processes: the API
(uvicorn) and analysis workers (``bench worker --analysis``).

Drill: a close-the-loop job is queued over HTTP; once a worker holds it (``running``), the worker is
frozen (SIGSTOP: it cannot finish while we look) and then it and the API are killed with SIGKILL.
A new API and a new worker come up: the job is claimed again (its heartbeat is stale), ends ``done``
and its report page is served as stored.  Also: a worker frozen past its lease whose job was re-run
by another finishes nothing and stores nothing when it wakes (fenced).
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import httpx
import pytest

from bench.jobs import JobRunner, enqueue
from bench.storage import open_database
from bench.storage.models import Analysis, Fit
from tests import synth
from tests.api_support import OPERATOR, TOKENS, VIEWER

DAY = [("hold", 3600), ("ramp", 60, 1.0), ("hold", 14400), ("ramp", -20, 0.5), ("hold", 14400),
       ("ramp", 45, 2.0), ("hold", 14400), ("ramp", 0, 1.0), ("hold", 14400), ("ramp", 30, 0.25)]
HIDDEN = {"gradient": 0.06, "rate": 0.08}
DEADLINE_S = 300.0          # generous: a loaded 2-core machine; the drill waits on states, never on time


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    return request.getfixturevalue("pg_url")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(db_url: str) -> dict[str, str]:
    tokens = ",".join(f"{role}:{token}" for token, role in TOKENS.items())
    return {**os.environ, "BENCH_DATABASE_URL": db_url, "BENCH_TOKENS": tokens}


def _start_api(db_url: str, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "--factory", "api.app:app_from_env", "--port",
                             str(port), "--log-level", "warning"], env=_env(db_url))
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the API process ended"
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise AssertionError("the API did not start")


def _start_worker(db_url: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bench", "worker", "--analysis", "--heartbeat", "0.2",
                             "--stale-after", "1.5", "--poll", "0.05", "--log-level", "warning"], env=_env(db_url))


def _wait(predicate, what: str, poll_s: float = 0.01):
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"timed out waiting for {what}")


def _job(db, job_id: int) -> Analysis:
    with db.session() as s:
        job = s.get(Analysis, job_id)
        s.expunge(job)
        return job


def _import_pair(db):
    from bench.commands.service import import_dataset

    train, _ = synth.make_run(DAY, HIDDEN, seed=1, dt=1.0)
    validate, _ = synth.make_run(synth.VALIDATE_PROFILE * 2, HIDDEN, seed=2, dt=1.0)
    return import_dataset(db, train, "G-DRILL"), import_dataset(db, validate, "G-DRILL")


def test_kill_api_and_worker_during_a_close_loop_job(db_url):
    db = open_database(db_url)
    procs: list[subprocess.Popen] = []
    try:
        train, val = _import_pair(db)
        port = _free_port()
        api = _start_api(db_url, port)
        procs.append(api)
        base = f"http://127.0.0.1:{port}"
        r = httpx.post(f"{base}/close-loop", json={"model": "static", "train_run_id": train,
                                                   "validation_run_id": val, "channels": ["x"]},
                       headers=OPERATOR, timeout=30)
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        worker = _start_worker(db_url)
        procs.append(worker)
        first = _wait(lambda: (j := _job(db, job_id)).status != "queued" and j, "the worker to claim the job")
        os.kill(worker.pid, signal.SIGSTOP)
        held = _job(db, job_id)
        assert held.status == "running" and held.attempts == 1, \
            f"the job must still be running when its worker is killed (it was {held.status})"
        for proc in (worker, api):
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
        procs.clear()
        # restart everything: a new API, a new worker; the job is claimed again once its heartbeat is stale
        port = _free_port()
        procs.append(_start_api(db_url, port))
        procs.append(_start_worker(db_url))
        base = f"http://127.0.0.1:{port}"
        doc = _wait(lambda: (d := httpx.get(f"{base}/close-loop/{job_id}", headers=VIEWER, timeout=30).json())
                    ["status"] in ("done", "failed") and d, "the job to end", poll_s=0.2)
        assert doc["status"] == "done", doc["error"]
        assert doc["attempts"] == 2 and doc["worker"] != first.worker
        assert doc["result"]["channels"]["x"]["verdict"]
        t0 = time.perf_counter()
        page = httpx.get(f"{base}{doc['report_url']}", headers=VIEWER, timeout=30)
        print(f"\n{db.dialect}: report page ({len(page.content) / 1e6:.1f} MB) served in "
              f"{(time.perf_counter() - t0) * 1e3:.0f} ms")
        assert page.status_code == 200 and page.text.lstrip().lower().startswith("<!doctype html")
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30)
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
        _wait(lambda: b.claim() is not None, "the job's lease to go stale")
        with db.session() as s:                              # B's claim, seen from the database
            assert s.get(Analysis, job_id).worker == "worker-b"
        from bench.analysis import fit_job
        b_outcome = fit_job(db, {"model": "static", "run_ids": [train]})
        assert b._finish(job_id, "done", outcome=b_outcome) == "done"
        assert a._finish(job_id, "done", outcome=fit_job(db, {"model": "static", "run_ids": [train]})) == "lost"
        with db.session() as s:
            job = s.get(Analysis, job_id)
            assert (job.status, job.worker, job.attempts) == ("done", "worker-b", 2)
            versions = {f.version for f in s.query(Fit).filter(Fit.gyro_id == "G-FENCE")}
        assert versions == {1}
    finally:
        db.dispose()

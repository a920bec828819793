"""Durable analysis jobs: fits, close-the-loop analyses and report rendering, queued in ``analyses`` by
the API and executed by workers (``bench worker --analysis``, or a bench worker between runs).

Claiming and fencing, as for runs
---------------------------------
A worker claims the oldest job that is ``queued``, or ``running`` with a heartbeat older than
``stale_after_s`` (its worker died), with one guarded ``UPDATE ... WHERE id = :id AND (that condition)``:
on PostgreSQL the row lock makes a second claimer re-check the condition and find it false; on SQLite
the write lock serialises claims.  While the job runs, a heartbeat thread refreshes ``heartbeat_at``
(``WHERE worker = me``).  The job ends with an ``UPDATE ... WHERE worker = me AND status = 'running'``,
and a fit job stores its fit rows in that same transaction: a worker that lost its lease (frozen past
``stale_after_s``, its job claimed by another) finishes nothing and stores nothing; it logs why.
A job claimed ``max_attempts`` times without finishing (it kills its workers) ends ``failed``.

Hold point (tests)
------------------
With ``hold_file`` (``BENCH_JOB_HOLD_FILE`` for ``bench worker --analysis``), a job whose analysis has run
stops before it finishes while that file exists: the worker writes ``<job id> <worker id>`` to
``<hold_file>.held`` once it got there and goes on (heartbeat kept) when the file is removed.  Tests kill
workers at that point, where the job is provably running and nothing of it is stored.
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from sqlalchemy import and_, or_, select, update

from bench.analysis import JOBS, AnalysisInputError, Outcome
from bench.errors import BenchError
from bench.storage import queries
from bench.storage.db import Database
from bench.storage.errors import StorageError
from bench.storage.models import Analysis, Fit, utcnow

log = logging.getLogger(__name__)
MAX_ATTEMPTS = 3


class LeaseLost(Exception):
    """The job is no longer this worker's (another worker claimed it after this one went stale)."""


def enqueue(session, kind: str, request: dict[str, Any], *, requested_by: str = "", gyro_id: str | None = None,
            fit_id: int | None = None) -> Analysis:
    """Queue a job (in the caller's transaction); a worker picks it up."""
    if kind not in JOBS:
        raise ValueError(f"job kind {kind!r}: use one of {sorted(JOBS)}")
    job = Analysis(kind=kind, gyro_id=gyro_id, request=request, status="queued", requested_by=requested_by,
                   created_at=utcnow(), fit_id=fit_id, attempts=0)
    session.add(job)
    session.flush()
    return job


def default_job_worker_id() -> str:
    return f"analysis@{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


def _update(entity):
    return update(entity).execution_options(synchronize_session=False)


def polled(step, who: str):
    """One step of a polling loop (claim and do one run or job); a database problem is logged and
    counts as "nothing done", so the loop waits and tries again."""
    try:
        return step()
    except StorageError as exc:
        log.warning("%s: database problem: %s", who, exc)
        return None


class LeaseHolder:
    """What every polling worker that holds database leases has: its id, the heartbeat period and the
    staleness limit of its leases (wall seconds), its poll period and its stop flag."""

    def __init__(self, db: Database, worker_id: str, heartbeat_s: float, stale_after_s: float,
                 poll_s: float) -> None:
        if stale_after_s <= 2 * heartbeat_s:
            raise ValueError(f"stale_after_s ({stale_after_s}) must exceed twice heartbeat_s ({heartbeat_s})")
        self.db = db
        self.worker_id = worker_id
        self.heartbeat_s = heartbeat_s
        self.stale_after_s = stale_after_s
        self.poll_s = poll_s
        self._stop = threading.Event()

    def stop(self) -> None:
        """Stop claiming new work (what is under way goes on to its end)."""
        self._stop.set()


class JobRunner(LeaseHolder):
    """Claims and executes analysis jobs: ``run_one()`` does one job if any is due; ``run_forever()``
    loops until ``stop()``.  ``heartbeat_s`` / ``stale_after_s`` are wall seconds."""

    def __init__(self, db: Database, *, worker_id: str | None = None, heartbeat_s: float = 1.0,
                 stale_after_s: float = 15.0, poll_s: float = 0.5, max_attempts: int = MAX_ATTEMPTS,
                 hold_file: str | None = None) -> None:
        super().__init__(db, worker_id or default_job_worker_id(), heartbeat_s, stale_after_s, poll_s)
        self.max_attempts = max_attempts
        self.hold_file = hold_file
        self.done: list[tuple[int, str]] = []

    def run_forever(self) -> None:
        log.info("job worker %s started", self.worker_id)
        while not self._stop.is_set():
            if polled(self.run_one, f"job worker {self.worker_id}") is None:
                self._stop.wait(self.poll_s)

    def run_pending(self) -> list[tuple[int, str]]:
        """Execute jobs until none is due; returns [(job id, status)] of those this call ended."""
        out = []
        while (job_id := self.run_one()) is not None:
            out.append(self.done[-1] if self.done and self.done[-1][0] == job_id else (job_id, "lost"))
        return out

    # ---- claiming -----------------------------------------------------------------------------
    def _claimable(self, limit: dt.datetime):
        return or_(Analysis.status == "queued",
                   and_(Analysis.status == "running",
                        or_(Analysis.heartbeat_at.is_(None), Analysis.heartbeat_at < limit)))

    def claim(self) -> tuple[int, str, dict[str, Any], int] | None:
        """(job id, kind, request, attempt) of the job this worker now holds, or None."""
        now = utcnow()
        limit = now - dt.timedelta(seconds=self.stale_after_s)
        with self.db.session() as s:
            ids = s.scalars(select(Analysis.id).where(self._claimable(limit)).order_by(Analysis.id).limit(8)).all()
            for job_id in ids:
                took = s.execute(_update(Analysis).where(Analysis.id == job_id, self._claimable(limit))
                                 .values(status="running", worker=self.worker_id, heartbeat_at=now, started_at=now,
                                         attempts=Analysis.attempts + 1)).rowcount
                if took != 1:
                    continue
                job = s.get(Analysis, job_id)
                s.refresh(job)
                if job.attempts > self.max_attempts:
                    job.status, job.finished_at = "failed", now
                    job.error = (f"abandoned: claimed {job.attempts - 1} times by workers that died before "
                                 f"finishing it")
                    log.error("job %s (%s) %s", job_id, job.kind, job.error)
                    continue
                if job.attempts > 1:
                    log.warning("job %s (%s): attempt %s by %s (the previous worker stopped heartbeating)",
                                job_id, job.kind, job.attempts, self.worker_id)
                return job.id, job.kind, dict(job.request or {}), job.attempts
        return None

    # ---- execution ----------------------------------------------------------------------------
    def run_one(self) -> int | None:
        claimed = self.claim()
        if claimed is None:
            return None
        job_id, kind, request, _attempt = claimed
        stop_beat = threading.Event()
        beat = threading.Thread(target=self._heartbeat_loop, args=(job_id, stop_beat), daemon=True,
                                name=f"heartbeat-job{job_id}")
        beat.start()
        outcome, error = None, None
        try:
            try:
                outcome = JOBS[kind](self.db, request)
            except (BenchError, ValueError, KeyError) as exc:
                error = str(exc) if isinstance(exc, AnalysisInputError) else f"{type(exc).__name__}: {exc}"
            except Exception as exc:  # noqa: BLE001 - the failure is the job's result, reported to the caller
                log.exception("job %s (%s) failed", job_id, kind)
                error = f"internal error {type(exc).__name__}: {exc}"
            self._hold_point(job_id)
            status = self._finish(job_id, "done" if error is None else "failed", outcome=outcome, error=error)
        finally:
            stop_beat.set()
            beat.join(timeout=10)
        self.done.append((job_id, status))
        return job_id

    def _hold_point(self, job_id: int) -> None:
        """Tests only: while ``hold_file`` exists, wait here (the job is running, its result not stored)."""
        if self.hold_file is None or not Path(self.hold_file).exists():
            return
        tmp = Path(self.hold_file + ".held.tmp")
        tmp.write_text(f"{job_id} {self.worker_id}")
        tmp.replace(self.hold_file + ".held")
        log.warning("job %s held before finishing while %s exists", job_id, self.hold_file)
        while Path(self.hold_file).exists():
            time.sleep(0.02)

    def _finish(self, job_id: int, status: str, *, outcome: Outcome | None = None, error: str | None = None) -> str:
        """End the job under this worker's lease; a fit job's rows are stored in the same transaction.
        Returns the status written, or "lost" when the job was no longer this worker's."""
        try:
            with self.db.session() as s:
                took = s.execute(_update(Analysis).where(Analysis.id == job_id, Analysis.worker == self.worker_id,
                                                         Analysis.status == "running")
                                 .values(status=status, error=error, finished_at=utcnow())).rowcount
                if took != 1:
                    raise LeaseLost(job_id)
                if outcome is not None:
                    result, fit_id = dict(outcome.result), None
                    if outcome.fits:
                        versions = queries.save_fits(s, outcome.gyro_id, outcome.run_ids or [], outcome.fits,
                                                     accepted=outcome.accept)
                        model = outcome.fits[0]["model"]
                        fit_id = s.scalar(select(Fit.id).where(Fit.gyro_id == outcome.gyro_id, Fit.model == model,
                                                               Fit.version == versions[model]).order_by(Fit.id))
                        result.update(fit_id=fit_id, version=versions[model], accepted=outcome.accept)
                    s.execute(_update(Analysis).where(Analysis.id == job_id).values(
                        result=result, report_html=outcome.report_html,
                        fit_id=fit_id if fit_id is not None else result.get("fit_id")))
        except LeaseLost:
            log.warning("job %s: worker %s lost its lease (another worker claimed the job after this one stopped "
                        "heartbeating); its result is discarded", job_id, self.worker_id)
            return "lost"
        return status

    def _heartbeat_loop(self, job_id: int, stop: threading.Event) -> None:
        while not stop.wait(self.heartbeat_s):
            try:
                with self.db.session() as s:
                    s.execute(_update(Analysis).where(Analysis.id == job_id, Analysis.worker == self.worker_id,
                                                      Analysis.status == "running").values(heartbeat_at=utcnow()))
            except Exception as exc:  # noqa: BLE001 - a heartbeat problem must not kill the thread
                log.warning("job %s heartbeat failed: %s: %s", job_id, type(exc).__name__, exc)

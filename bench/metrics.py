"""Prometheus metrics of the bench service (text exposition format, names prefixed ``bench_``).

Read at scrape time, nothing is counted twice: the database holds the truth about runs, frames, gaps,
suspensions and jobs, so ``GET /metrics`` of the API and every worker's ``--metrics-port`` answer
from it (a worker: for its own bench); what only a process knows - frames and rows accepted but not
yet committed (``FrameWriter`` buffers), writer retries, the runs this worker executed - comes from
the process itself.

Families (labels):

* ``bench_runs{bench,status}``                   runs per status (gauge)
* ``bench_queue_depth{bench}``                   queued runs (gauge)
* ``bench_frames_stored_total{bench}``           gyro frames stored (counter)
* ``bench_frames_lost_total{bench}``             frames known missing in recorded gaps (counter)
* ``bench_gaps_total{bench,reason}``             gaps recorded (counter)
* ``bench_suspensions_total{bench}``             run suspensions (counter); ``bench_suspended_runs{bench}`` open ones
* ``bench_run_duration_seconds{bench}``          wall time of finished runs, start to end (summary)
* ``bench_jobs{kind,status}``                    API jobs (close-the-loop analyses) per status (gauge)
* ``bench_job_duration_seconds{kind}``           wall time of finished jobs, request to result (summary)
* ``bench_worker_heartbeat_age_seconds{bench}``  age of the bench's worker heartbeat (gauge)
* ``bench_frames_buffered{run}`` / ``bench_rows_buffered{run}`` / ``bench_frame_writer_retries_total{run}``
  this process's frame writers (not yet committed data; failed write attempts)
* ``bench_worker_runs_total{bench,status}`` / ``bench_worker_busy{bench}``  a worker's own runs

Public API::

    api_registry(db) -> CollectorRegistry
    worker_registry(worker) -> CollectorRegistry
    exposition(registry) -> (bytes, content type)
    serve_worker_metrics(worker, port, addr="127.0.0.1") -> (server, thread)
"""
from __future__ import annotations

import datetime as dt
from collections import defaultdict
from typing import Any, Iterable

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric, SummaryMetricFamily
from sqlalchemy import case, func, select

from bench.storage.db import Database
from bench.storage.frames import live_writer_statuses
from bench.storage.models import Analysis, Bench, FrameCursor, Gap, Run, RunStatus, Suspension

NO_BENCH = "none"          # label of runs that belong to no bench (bench run on the command line, imports)
FINAL_STATUSES = ("completed", "aborted", "failed")


def _utc(value: dt.datetime | None) -> dt.datetime | None:
    if value is None:
        return None
    return value if value.tzinfo else value.replace(tzinfo=dt.timezone.utc)


def _seconds(start: dt.datetime | None, end: dt.datetime | None) -> float | None:
    s, e = _utc(start), _utc(end)
    return (e - s).total_seconds() if s and e else None


class DatabaseCollector:
    """Everything the database knows; ``bench`` limits it to one bench (a worker's view)."""

    def __init__(self, db: Database, bench: str | None = None) -> None:
        self.db = db
        self.bench = bench

    def describe(self) -> list[Metric]:
        return []            # no database query when the collector is registered

    def _where(self, stmt):
        return stmt.where(Bench.name == self.bench) if self.bench is not None else stmt

    def collect(self) -> Iterable[Metric]:
        bench_name = func.coalesce(Bench.name, NO_BENCH)
        with self.db.engine.connect() as conn:
            runs = conn.execute(self._where(select(bench_name, Run.status, func.count())
                                            .select_from(Run).outerjoin(Bench, Run.bench_id == Bench.id)
                                            .group_by(bench_name, Run.status))).all()
            frames = conn.execute(self._where(select(bench_name, func.sum(FrameCursor.next_index))
                                              .select_from(FrameCursor).join(Run, FrameCursor.run_id == Run.id)
                                              .outerjoin(Bench, Run.bench_id == Bench.id)
                                              .group_by(bench_name))).all()
            gaps = conn.execute(self._where(select(bench_name, Gap.reason, func.count(), func.sum(Gap.frames_missing))
                                            .select_from(Gap).join(Run, Gap.run_id == Run.id)
                                            .outerjoin(Bench, Run.bench_id == Bench.id)
                                            .group_by(bench_name, Gap.reason))).all()
            susp = conn.execute(self._where(select(bench_name, func.count(),
                                                   func.sum(case((Suspension.t_to.is_(None), 1), else_=0)))
                                            .select_from(Suspension).join(Run, Suspension.run_id == Run.id)
                                            .outerjoin(Bench, Run.bench_id == Bench.id)
                                            .group_by(bench_name))).all()
            finished = conn.execute(self._where(select(bench_name, Run.started_at, Run.finished_at)
                                                .select_from(Run).outerjoin(Bench, Run.bench_id == Bench.id)
                                                .where(Run.status.in_(FINAL_STATUSES),
                                                       Run.started_at.is_not(None), Run.finished_at.is_not(None)))).all()
            benches = conn.execute(self._where(select(Bench.name, Bench.heartbeat_at))).all()
            jobs = conn.execute(select(Analysis.kind, Analysis.status, Analysis.created_at, Analysis.finished_at)
                                ).all() if self.bench is None else []

        known = sorted({b.name for b in benches})
        g = GaugeMetricFamily("bench_runs", "Runs per status", labels=["bench", "status"])
        seen = defaultdict(int)
        for name, status, n in runs:
            seen[(name, status)] += int(n)
        for name in known:                 # every status of every bench, zeros included: rates need series
            for status in (s.value for s in RunStatus):
                seen.setdefault((name, status), 0)
        for (name, status), n in sorted(seen.items()):
            g.add_metric([name, status], n)
        yield g

        q = GaugeMetricFamily("bench_queue_depth", "Runs queued and not yet claimed", labels=["bench"])
        for name in sorted({k[0] for k in seen}):
            q.add_metric([name], seen.get((name, RunStatus.QUEUED.value), 0))
        yield q

        c = CounterMetricFamily("bench_frames_stored", "Gyro frames stored", labels=["bench"])
        stored = {name: int(total or 0) for name, total in frames}
        for name in sorted(set(stored) | set(known)):
            c.add_metric([name], stored.get(name, 0))
        yield c

        lost = CounterMetricFamily("bench_frames_lost", "Frames known missing in recorded gaps", labels=["bench"])
        gap_c = CounterMetricFamily("bench_gaps", "Gaps (time with missing frames) recorded", labels=["bench", "reason"])
        lost_by = defaultdict(int)
        for name, reason, n, missing in gaps:
            gap_c.add_metric([name, reason], int(n))
            lost_by[name] += int(missing or 0)
        for name in sorted(set(lost_by) | set(known)):
            lost.add_metric([name], lost_by.get(name, 0))
        yield gap_c
        yield lost

        s_c = CounterMetricFamily("bench_suspensions", "Run suspensions", labels=["bench"])
        s_open = GaugeMetricFamily("bench_suspended_runs", "Suspensions still open", labels=["bench"])
        s_by = {name: (int(n), int(o or 0)) for name, n, o in susp}
        for name in sorted(set(s_by) | set(known)):
            n, o = s_by.get(name, (0, 0))
            s_c.add_metric([name], n)
            s_open.add_metric([name], o)
        yield s_c
        yield s_open

        dur = SummaryMetricFamily("bench_run_duration_seconds", "Wall time of finished runs", labels=["bench"])
        d_by: dict[str, list[float]] = defaultdict(list)
        for name, started, ended in finished:
            sec = _seconds(started, ended)
            if sec is not None:
                d_by[name].append(sec)
        for name in sorted(set(d_by) | set(known)):
            vals = d_by.get(name, [])
            dur.add_metric([name], count_value=len(vals), sum_value=float(sum(vals)))
        yield dur

        now = dt.datetime.now(dt.timezone.utc)
        hb = GaugeMetricFamily("bench_worker_heartbeat_age_seconds", "Age of the bench worker's last heartbeat",
                               labels=["bench"])
        for name, beat in benches:
            if beat is not None:
                hb.add_metric([name], max(0.0, (now - _utc(beat)).total_seconds()))
        yield hb

        if self.bench is None:
            jg = GaugeMetricFamily("bench_jobs", "API jobs (analyses) per status", labels=["kind", "status"])
            jd = SummaryMetricFamily("bench_job_duration_seconds", "Wall time of finished jobs", labels=["kind"])
            counts: dict[tuple[str, str], int] = defaultdict(int)
            times: dict[str, list[float]] = defaultdict(list)
            for kind, status, created, ended in jobs:
                counts[(kind, status)] += 1
                sec = _seconds(created, ended)
                if sec is not None:
                    times[kind].append(sec)
            for (kind, status), n in sorted(counts.items()):
                jg.add_metric([kind, status], n)
            for kind in sorted({k for k, _ in counts}):
                jd.add_metric([kind], count_value=len(times[kind]), sum_value=float(sum(times[kind])))
            yield jg
            yield jd


class WriterCollector:
    """This process's frame writers: data accepted but not committed, failed write attempts."""

    def describe(self) -> list[Metric]:
        return []

    def collect(self) -> Iterable[Metric]:
        frames = GaugeMetricFamily("bench_frames_buffered", "Frames held in memory, not yet committed", labels=["run"])
        rows = GaugeMetricFamily("bench_rows_buffered", "Other rows held in memory, not yet committed", labels=["run"])
        retries = CounterMetricFamily("bench_frame_writer_retries", "Failed database write attempts", labels=["run"])
        for st in live_writer_statuses():
            run = str(st.run_id)
            frames.add_metric([run], st.buffered_frames)
            rows.add_metric([run], st.buffered_rows)
            retries.add_metric([run], st.retries)
        yield frames
        yield rows
        yield retries


class WorkerCollector:
    """A worker's own view: the runs it executed and whether it is busy."""

    def __init__(self, worker: Any) -> None:
        self.worker = worker

    def describe(self) -> list[Metric]:
        return []

    def collect(self) -> Iterable[Metric]:
        name = self.worker.bench_name
        done = CounterMetricFamily("bench_worker_runs", "Runs this worker executed, by final status",
                                   labels=["bench", "status"])
        counts: dict[str, int] = defaultdict(int)
        for _run, status in list(self.worker.runs_done):
            counts[status] += 1
        for status, n in sorted(counts.items()):
            done.add_metric([name, status], n)
        yield done
        busy = GaugeMetricFamily("bench_worker_busy", "1 while the worker executes a run", labels=["bench"])
        busy.add_metric([name], 1 if self.worker.current_run is not None else 0)
        yield busy


def api_registry(db: Database) -> CollectorRegistry:
    reg = CollectorRegistry(auto_describe=False)
    reg.register(DatabaseCollector(db))
    reg.register(WriterCollector())
    return reg


def worker_registry(worker: Any) -> CollectorRegistry:
    reg = CollectorRegistry(auto_describe=False)
    reg.register(DatabaseCollector(worker.db, bench=worker.bench_name))
    reg.register(WriterCollector())
    reg.register(WorkerCollector(worker))
    return reg


def exposition(registry: CollectorRegistry) -> tuple[bytes, str]:
    return generate_latest(registry), CONTENT_TYPE_LATEST


def serve_worker_metrics(worker: Any, port: int, addr: str = "127.0.0.1"):
    """HTTP server (its own thread) answering the worker's metrics; port 0 picks a free port
    (``server.server_port``).  Returns (server, thread)."""
    return start_http_server(port, addr=addr, registry=worker_registry(worker))

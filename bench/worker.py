"""The bench worker: takes the runs queued for its bench from the database and executes them with the
run engine, one at a time, heartbeating while it does.  Between runs it executes the analysis jobs
queued by the API (``bench.jobs``), unless built with ``run_jobs=False``.

Claiming (one run per bench at a time)
--------------------------------------
Each bench row carries a *lease*: ``benches.worker`` and ``benches.heartbeat_at``.  A worker first
writes the lease (an ``UPDATE`` of the bench row, which row-locks it on PostgreSQL and takes the
write lock on SQLite, so claims for one bench are serialised) and only proceeds when no other worker
holds a fresh lease.  Then, in the same transaction:

1. a run of the bench still marked active (running / paused / stopping / suspended) whose heartbeat
   is stale (its worker died) is taken over (guarded ``UPDATE ... WHERE heartbeat_at < limit``) and
   **resumed** from its checkpoint with ``Engine.resume``;
2. else the next due ``queued`` run of the bench is claimed with ``queries.claim_next_run`` (scheduled
   runs by ``start_at`` once due, then unscheduled runs in order of creation; ``SELECT ... FOR UPDATE
   SKIP LOCKED`` on PostgreSQL, then ``UPDATE ... WHERE status = 'queued'``, which is the whole guard
   on SQLite) and started with ``Engine.run``.

While a run executes, a heartbeat thread refreshes ``runs.heartbeat_at``, the bench lease and the
run's live progress document (``runs.live``: percent, step, remaining bench time, ETA on the wall
clock).  Operator requests reach the engine through ``DbControl``, which consumes the
``run_requests`` rows the API writes, in order.

The engine persists through ``bench.engine.sqlstore.SqlRunStore`` (the ``RunStore`` over
``bench.storage``); the drivers come from ``bench.engine.factory.build_devices`` unless a
``devices_factory`` is given; the ``Fit`` step stores its fits with ``factory.make_fit_hook``
(accepted: the newest fit from a completed procedure becomes the gyro's coefficients).
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import socket
import threading
import time
import uuid
from typing import Any, Callable

from sqlalchemy import select, update

from bench.clock import Clock
from bench.config import BenchConfig
from bench.engine import Devices, Engine, EngineConfig
from bench.engine.factory import build_devices, close_devices, engine_config_for, make_fit_hook
from bench.engine.lease import RunLease, fence_devices
from bench.engine.sqlstore import SqlRunStore
from bench.errors import BenchError, LeaseLost
from bench.jobs import JobRunner, LeaseHolder, polled
from bench.jsonsafe import jsonable
from bench.storage import queries
from bench.storage.db import Database
from bench.storage.errors import StorageError
from bench.storage.models import Bench, Run, RunRequest, RunStatus, utcnow

log = logging.getLogger(__name__)

ACTIVE = tuple(sorted(queries.ACTIVE))
TERMINAL = tuple(sorted(queries.TERMINAL))
LOST = "lost"          # execute()'s answer when another worker took the run over
DevicesFactory = Callable[[BenchConfig], Devices]


# ================================================================================================
# Control
# ================================================================================================
class DbControl:
    """``bench.engine.Control`` over ``run_requests``: the oldest unconsumed request of the run, marked
    consumed as it is handed over.  The database is asked at most every ``min_interval_s`` wall
    seconds (the engine polls once per tick, which may be many times a second at high speed).
    ``publish`` (the worker's progress publisher) is called from here every ``publish_s`` so the run
    row's ``live`` document is only ever rewritten by the engine's own thread (no lost updates)."""

    def __init__(self, db: Database, run_id: int, min_interval_s: float = 0.2,
                 publish: Callable[[], None] | None = None, publish_s: float = 1.0, lease: RunLease | None = None) -> None:
        self.db = db
        self.lease = lease          # a worker that lost the run consumes none of its requests
        self.run_id = int(run_id)
        self.min_interval_s = min_interval_s
        self._next = 0.0
        self.publish = publish
        self.publish_s = publish_s
        self._next_publish = 0.0

    def poll(self) -> str | None:
        if self.lease is not None:
            self.lease.check()
        now = time.monotonic()
        if self.publish is not None and now >= self._next_publish:
            # progress is published from the engine's thread, between its own writes of the run row
            self._next_publish = now + self.publish_s
            self.publish()
        if now < self._next:
            return None
        with self.db.session() as s:
            req = s.scalars(select(RunRequest).where(RunRequest.run_id == self.run_id,
                                                     RunRequest.consumed_at.is_(None))
                            .order_by(RunRequest.id).limit(1)).first()
            if req is None:
                self._next = now + self.min_interval_s
                return None
            took = s.execute(_update(RunRequest).where(RunRequest.id == req.id, RunRequest.consumed_at.is_(None))
                             .values(consumed_at=utcnow())).rowcount
            return req.command if took == 1 else None


# ================================================================================================
# The worker
# ================================================================================================
def _as_utc(value: dt.datetime | None) -> dt.datetime | None:
    if value is not None and value.tzinfo is None:        # SQLite hands back naive datetimes
        return value.replace(tzinfo=dt.timezone.utc)
    return value


def default_worker_id(bench_name: str) -> str:
    return f"{bench_name}@{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


class Worker(LeaseHolder):
    """Serves one bench: ``run_forever()`` claims and executes runs until ``stop()``.

    ``devices_factory(config) -> Devices`` opens the drivers for a run (closed after it; None = the real
    drivers of ``bench.engine.factory.build_devices``); ``engine_config`` defaults to
    ``engine_config_for(clock)``;
    ``clock`` is the bench clock shared with the devices (a simulated bench's lockstep clock);
    ``bench_state`` the simulated bench itself, whose physical state goes into the run's checkpoints.
    ``heartbeat_s`` / ``stale_after_s`` are wall seconds: a run or bench lease whose heartbeat is older
    than ``stale_after_s`` belongs to a dead worker.
    """

    def __init__(self, db: Database, bench_name: str, config: BenchConfig, devices_factory: DevicesFactory | None,
                 clock: Clock, *, engine_config: EngineConfig | None = None, worker_id: str | None = None,
                 heartbeat_s: float = 1.0, stale_after_s: float = 15.0, poll_s: float = 0.5,
                 accept_fits: bool = True, writer_options: dict[str, Any] | None = None,
                 run_jobs: bool = True, bench_state: Any = None) -> None:
        super().__init__(db, worker_id or default_worker_id(bench_name), heartbeat_s, stale_after_s, poll_s)
        self.bench_name = bench_name
        self.config = config
        self.devices_factory = devices_factory or (lambda cfg: build_devices(cfg, clock))
        self.clock = clock
        self.bench_state = bench_state
        self.engine_config = engine_config or engine_config_for(clock)
        self.accept_fits = accept_fits
        self.writer_options = writer_options
        # between runs the worker executes analysis jobs (fits, close-the-loop, reports) under their own
        # leases; run_jobs=False leaves them to `bench worker --analysis`
        self.jobs = JobRunner(db, worker_id=f"{self.worker_id}/jobs", heartbeat_s=heartbeat_s,
                              stale_after_s=stale_after_s) if run_jobs else None
        self.current_run: int | None = None
        self.lease: RunLease | None = None
        self.engine: Engine | None = None
        self.runs_done: list[tuple[int, str]] = []
        with db.session() as s:
            queries.ensure_bench(s, bench_name, _config_doc(config))

    # ---- lifecycle ----------------------------------------------------------------------------
    def run_forever(self) -> None:
        log.info("worker %s serving bench %s", self.worker_id, self.bench_name)
        try:
            while not self._stop.is_set():
                did = polled(self.run_once, f"worker {self.worker_id}")
                if did is None and self.jobs is not None and not self._stop.is_set():
                    did = polled(self.jobs.run_one, f"worker {self.worker_id} (job queue)")
                if did is None:
                    self._stop.wait(self.poll_s)
        finally:
            self._release_lease()

    def start_thread(self) -> threading.Thread:
        t = threading.Thread(target=self.run_forever, name=f"worker-{self.bench_name}", daemon=True)
        t.start()
        return t

    # ---- claiming -----------------------------------------------------------------------------
    def claim(self) -> tuple[int, bool] | None:
        """(run id, resume?) of the run this worker now owns, or None (nothing due, or the bench is
        served by another live worker)."""
        now = utcnow()
        limit = now - dt.timedelta(seconds=self.stale_after_s)
        with self.db.session() as s:
            bench = s.scalars(select(Bench).where(Bench.name == self.bench_name)).first()
            if bench is None:
                bench = queries.ensure_bench(s, self.bench_name, _config_doc(self.config))
            # the lease: this UPDATE locks the bench row (PostgreSQL) / the database (SQLite) till commit
            took = s.execute(_update(Bench).where(
                Bench.id == bench.id,
                (Bench.worker.is_(None)) | (Bench.worker == self.worker_id) | (Bench.heartbeat_at.is_(None))
                | (Bench.heartbeat_at < limit)).values(worker=self.worker_id, heartbeat_at=now)).rowcount
            if took != 1:
                return None
            active = s.scalars(select(Run).where(Run.bench_id == bench.id, Run.status.in_(ACTIVE),
                                                 Run.parent_id.is_(None)).order_by(Run.id)).all()
            for run in active:
                if run.worker != self.worker_id and _as_utc(run.heartbeat_at) is not None \
                        and _as_utc(run.heartbeat_at) >= limit:
                    return None        # another worker's run is alive: one run per bench
            for run in active:
                got = s.execute(_update(Run).where(
                    Run.id == run.id, Run.status.in_(ACTIVE),
                    (Run.heartbeat_at.is_(None)) | (Run.heartbeat_at < limit) | (Run.worker == self.worker_id))
                    .values(worker=self.worker_id, heartbeat_at=now)).rowcount
                if got == 1:
                    queries.own_units(s, run.id, self.worker_id, now)
                    queries.add_event(s, run.id, "worker_takeover",
                                      f"worker {self.worker_id} takes over run {run.id} from "
                                      f"{run.worker or 'nobody'} (heartbeat stale) and resumes it",
                                      data={"previous_worker": run.worker})
                    return run.id, True
            run = queries.claim_next_run(s, self.worker_id, bench_id=bench.id, now=now,
                                         config_snapshot=_config_doc(self.config))
            if run is None:
                return None
            run_id = run.id
            queries.add_event(s, run_id, "worker_claimed", f"worker {self.worker_id} claimed run {run_id}")
            return run_id, False

    def run_once(self) -> int | None:
        """Claim one run and execute it to its end; returns its id, or None when nothing was due."""
        claimed = self.claim()
        if claimed is None:
            self._bench_state({"state": "idle"})
            return None
        run_id, resume = claimed
        self.execute(run_id, resume)
        return run_id

    # ---- execution ----------------------------------------------------------------------------
    def execute(self, run_id: int, resume: bool) -> str:
        import procedures

        with self.db.session() as s:
            run = queries.get_run(s, run_id)
            procedure, params, has_checkpoint = run.procedure, dict(run.parameters or {}), run.checkpoint is not None
        store = SqlRunStore(self.db, geometry=self.config.turntable.geometry, frame_kind=self.config.gyro.frame,
                            nominal_rate_hz=self.config.gyro.data_rate_hz, writer_options=self.writer_options)
        self.current_run = run_id
        lease = self.lease = RunLease(self.db, run_id, self.worker_id, self.stale_after_s)
        store.lease = lease
        stop_beat = threading.Event()
        beat = threading.Thread(target=self._heartbeat_loop, args=(run_id, stop_beat), daemon=True,
                                name=f"heartbeat-run{run_id}")
        devices = None
        status = RunStatus.FAILED.value
        try:
            devices = self.devices_factory(self.config)
            control = DbControl(self.db, run_id, publish=lambda: self._publish_progress(run_id),
                                publish_s=self.heartbeat_s, lease=lease)
            engine = Engine(fence_devices(devices, lease), store, self.clock, self.config, control,
                            self.engine_config,
                            make_fit_hook(self.db, store, latitude_deg=self.config.latitude_deg, accept=self.accept_fits),
                            bench_state=self.bench_state)
            self.engine = engine
            beat.start()
            if resume and has_checkpoint:
                status = engine.resume(str(run_id))
            else:
                module = procedures.get(procedure)
                plan = module.build(module.Params.model_validate(params))
                status = engine.run(str(run_id), plan)
        except LeaseLost as exc:      # another worker owns the run now: touch neither it nor the hardware
            status = LOST
            log.warning("run %s: %s; leaving the run loop", run_id, exc)
        except BenchError as exc:     # before the engine took over (devices, plan): the run fails here
            status = RunStatus.FAILED.value
            self._fail(run_id, f"{type(exc).__name__}: {exc}")
        except Exception as exc:      # noqa: BLE001 - the worker must outlive one run's internal error
            log.exception("run %s ended by an internal error", run_id)
            self._fail(run_id, f"internal error {type(exc).__name__}: {exc}")
        finally:
            stop_beat.set()
            if beat.is_alive():
                beat.join(timeout=10)
            try:
                store.close(run_id)
            except StorageError as exc:
                log.error("run %s: could not store the last data: %s", run_id, exc)
            if devices is not None:
                for problem in close_devices(devices):
                    log.warning("run %s: closing devices: %s", run_id, problem)
            self.engine = None
            self.current_run = None
            self.lease = None
        self.runs_done.append((run_id, status))
        return status

    def _fail(self, run_id: int, reason: str) -> None:
        with self.db.session() as s:
            run = queries.get_run(s, run_id, for_update=True)
            if run.worker != self.worker_id:
                log.warning("run %s: not marked failed (%s): worker %s owns it now", run_id, reason, run.worker)
                return
            if run.status not in TERMINAL:
                run.status, run.finished_at, run.error = RunStatus.FAILED.value, utcnow(), reason
                queries.add_event(s, run_id, "run_failed", reason)

    # ---- heartbeat ----------------------------------------------------------------------------
    def _heartbeat_loop(self, run_id: int, stop: threading.Event) -> None:
        while True:
            try:
                self._heartbeat(run_id)
            except Exception as exc:  # noqa: BLE001 - a heartbeat problem must not kill the thread
                log.warning("run %s heartbeat failed: %s: %s", run_id, type(exc).__name__, exc)
            if stop.wait(self.heartbeat_s):
                return

    def _heartbeat(self, run_id: int) -> None:
        """Liveness only: single-column updates of the run and the bench lease (never ``live``)."""
        now = utcnow()
        lease = self.lease
        with self.db.session() as s:
            took = s.execute(_update(Run).where(Run.id == run_id, Run.worker == self.worker_id)
                             .values(heartbeat_at=now)).rowcount
            if lease is not None and lease.run_id == run_id:
                if took == 1:
                    lease.confirm()
                else:
                    lease.lose(s.scalar(select(Run.worker).where(Run.id == run_id)))
                    return
            s.execute(_update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                      .values(heartbeat_at=now, state={"state": "busy", "run_id": run_id, "worker": self.worker_id}))

    def _publish_progress(self, run_id: int) -> None:
        """The engine's progress, ETA on the wall clock and the bench speed into ``runs.live``."""
        engine = self.engine
        if engine is None or engine.plan is None:
            return
        try:
            progress = engine.progress()
        except Exception:  # noqa: BLE001 - progress is advisory; the engine may be between steps
            return
        now = utcnow()
        measured = getattr(self.clock, "effective_speed", None)     # lockstep: what the host achieves
        speed = (measured() if measured else None) or getattr(self.clock, "speed", 1.0)
        finite_speed = speed if speed and speed != float("inf") else None
        remaining = float(progress.get("remaining_bench_s") or 0.0)
        wall_left = remaining / finite_speed if finite_speed else 0.0
        with self.db.session() as s:
            run = queries.get_run(s, run_id, for_update=True)
            if run.status in TERMINAL or run.worker != self.worker_id:
                return
            run.live = {**(run.live or {}), "progress": jsonable(progress),
                        "eta_utc": (now + dt.timedelta(seconds=wall_left)).isoformat(),
                        "bench_speed": finite_speed, "updated_utc": now.isoformat()}
            run.progress = min(1.0, max(0.0, float(progress.get("percent", 0.0)) / 100.0))
            run.current_step = int(progress.get("step_index", 0))

    def _bench_state(self, state: dict[str, Any]) -> None:
        with self.db.session() as s:
            s.execute(_update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                      .values(heartbeat_at=utcnow(), state={**state, "worker": self.worker_id}))

    def _release_lease(self) -> None:
        try:
            with self.db.session() as s:
                s.execute(_update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                          .values(worker=None, heartbeat_at=None, state={"state": "offline"}))
        except StorageError as exc:
            log.warning("worker %s: could not release the bench lease: %s", self.worker_id, exc)


def _update(entity):
    """``UPDATE`` whose guard is evaluated by the database only (no in-session evaluation: SQLite hands
    back naive datetimes the ORM cannot compare with aware ones)."""
    return update(entity).execution_options(synchronize_session=False)


def _config_doc(config: BenchConfig) -> dict[str, Any]:
    import json
    return json.loads(config.model_dump_json())

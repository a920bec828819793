"""The bench worker: takes the runs queued for its bench from the database and executes them with the
run engine, one at a time, heartbeating while it does.

Claiming (one run per bench at a time)
--------------------------------------
Each bench row carries a *lease*: ``benches.worker`` and ``benches.heartbeat_at``.  A worker first
writes the lease (an ``UPDATE`` of the bench row, which row-locks it on PostgreSQL and takes the
write lock on SQLite, so claims for one bench are serialised) and only proceeds when no other worker
holds a fresh lease.  Then, in the same transaction:

1. a run of the bench still marked active (running / paused / stopping / suspended) whose heartbeat
   is stale (its worker died) is taken over (guarded ``UPDATE ... WHERE heartbeat_at < limit``) and
   **resumed** from its checkpoint with ``Engine.resume``;
2. else the oldest due ``queued`` run of the bench is claimed (``SELECT ... FOR UPDATE SKIP LOCKED``
   on PostgreSQL, then ``UPDATE ... WHERE status = 'queued'``, which is the whole guard on SQLite)
   and started with ``Engine.run``.

While a run executes, a heartbeat thread refreshes ``runs.heartbeat_at``, the bench lease and the
run's live progress document (``runs.live``: percent, step, remaining bench time, ETA on the wall
clock).  Operator requests reach the engine through ``DbControl``, which consumes the
``run_requests`` rows the API writes, in order.

The engine persists through ``SqlRunStore``, the ``bench.engine.RunStore`` adapter over
``bench.storage`` (frames, probe readings, telemetry, events, segments and gaps go through one
batched ``FrameWriter`` per run so they survive short database outages).
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import socket
import threading
import time
import uuid
from typing import Any, Callable, Sequence

from sqlalchemy import select, update

from bench.clock import Clock
from bench.config import BenchConfig
from bench.engine import Devices, Engine, EngineConfig
from bench.engine.store import PsuReading
from bench.errors import BenchError
from bench.interfaces import AxisState, ChamberStatus, GyroFrame, ProbeReading
from bench.storage import FrameWriter, queries
from bench.storage.db import Database
from bench.storage.errors import InvalidTransition, StorageError
from bench.storage.models import Bench, FrameCursor, Run, RunRequest, Step, Suspension, utcnow

log = logging.getLogger(__name__)

ACTIVE = ("running", "paused", "stopping", "suspended")
TERMINAL = ("completed", "aborted", "failed")
# engine segment kinds -> storage segment kinds (storage knows soak, record, ramp, settle, move)
SEGMENT_KIND = {"record": "record", "soak": "soak", "ramp": "ramp", "wait_stable": "settle",
                "table_rate": "record", "orient": "move"}
DevicesFactory = Callable[[BenchConfig], Devices]


# ================================================================================================
# RunStore adapter
# ================================================================================================
class SqlRunStore:
    """``bench.engine.RunStore`` over the runs database.  Engine run ids are the decimal text of
    ``runs.id``; the run row must exist (the API creates it, the worker claims it).

    Status mapping: the engine's ``stopped`` (ended early on an operator stop, after finishing the
    current recording) is stored as ``completed`` with ``runs.live["outcome"] = "stopped"``; every
    other engine status is stored as is.  The engine is the authority on a run it executes, so
    status changes are written directly; only leaving a terminal status is refused.
    """

    def __init__(self, db: Database, *, frame_kind: str = "kvh_a", nominal_rate_hz: float | None = None,
                 writer_options: dict[str, Any] | None = None) -> None:
        self.db = db
        self.frame_kind = frame_kind
        self.nominal_rate_hz = nominal_rate_hz
        self.writer_options = dict(writer_options or {})
        self._writers: dict[int, FrameWriter] = {}
        self._lock = threading.Lock()

    # ---- writers ----------------------------------------------------------------------------
    def writer(self, run_id: str | int) -> FrameWriter:
        rid = int(run_id)
        with self._lock:
            w = self._writers.get(rid)
            if w is None:
                opts: dict[str, Any] = {"frame_kind": self.frame_kind, "nominal_rate_hz": self.nominal_rate_hz}
                if self.frame_kind != "kvh_a":
                    opts.update(valid_status=None)
                opts.update(self.writer_options)
                w = self._writers[rid] = FrameWriter(self.db, rid, **opts)
            return w

    def flush(self, run_id: str | int, timeout: float = 60.0) -> None:
        w = self._writers.get(int(run_id))
        if w is not None:
            w.flush(timeout)

    def close(self, run_id: str | int, timeout: float = 60.0) -> None:
        with self._lock:
            w = self._writers.pop(int(run_id), None)
        if w is not None:
            w.close(timeout)

    def abandon(self, run_id: str | int) -> None:
        with self._lock:
            w = self._writers.pop(int(run_id), None)
        if w is not None:
            w.abandon()

    # ---- run --------------------------------------------------------------------------------
    def create_run(self, run_id: str, plan: dict[str, Any], summary: dict[str, Any], t: float) -> None:
        rid = int(run_id)
        with self.db.session() as s:
            run = queries.get_run(s, rid, for_update=True)
            live = dict(run.live or {})
            live.update(plan=plan, summary=summary, started_t=t)
            run.live = live
            existing = s.scalar(select(Step.id).where(Step.run_id == rid).limit(1))
            if existing is None:      # a restart before the first checkpoint keeps the steps it made
                queries.add_steps(s, rid, [{"name": st.get("kind", "step"), "kind": st.get("kind", "step"),
                                            "params": st} for st in plan.get("steps", [])])

    def load_plan(self, run_id: str) -> dict[str, Any]:
        with self.db.session() as s:
            run = queries.get_run(s, int(run_id))
            plan = (run.live or {}).get("plan")
        if plan is None:
            raise StorageError(f"run {run_id}: no plan stored (the run never started)")
        return plan

    def set_run_status(self, run_id: str, status: str, t: float, reason: str | None = None) -> None:
        rid = int(run_id)
        stored = "completed" if status == "stopped" else status
        with self.db.session() as s:
            run = queries.get_run(s, rid, for_update=True)
            if run.status in TERMINAL and stored != run.status:
                raise InvalidTransition(f"run {rid} already ended ({run.status}); cannot become {status!r}")
            now = utcnow()
            run.status = stored
            if stored == "running" and run.started_at is None:
                run.started_at = now
            if stored in TERMINAL:
                run.finished_at = now
                if stored != "completed" and reason:
                    run.error = reason
            live = dict(run.live or {})
            live.update(engine_status=status, status_t=t, status_reason=reason)
            if stored in TERMINAL:
                live["outcome"] = status
            run.live = live

    def save_checkpoint(self, run_id: str, checkpoint: dict[str, Any]) -> None:
        progress = (checkpoint.get("progress") or {}).get("percent")
        with self.db.session() as s:
            queries.save_checkpoint(s, int(run_id), checkpoint, current_step=int(checkpoint.get("step_index", 0)),
                                    progress=None if progress is None else min(1.0, max(0.0, progress / 100.0)))

    def load_checkpoint(self, run_id: str) -> dict[str, Any] | None:
        with self.db.session() as s:
            return queries.get_run(s, int(run_id)).checkpoint

    def set_step_status(self, run_id: str, index: int, kind: str, status: str, t: float,
                        info: dict[str, Any] | None = None) -> None:
        with self.db.session() as s:
            step = s.scalars(select(Step).where(Step.run_id == int(run_id), Step.index == index)).first()
            if step is None:
                raise StorageError(f"run {run_id} has no step {index}")
            step.status = status
            if status == "running":
                step.started_t = t
            else:
                step.finished_t = t
            if info:
                step.params = {**(step.params or {}), "info": info}

    def add_event(self, run_id: str, t: float, level: str, kind: str, message: str,
                  data: dict[str, Any] | None = None) -> None:
        self.writer(run_id).add_event(kind[:32], message, t_bench=t, data={"level": level, **(data or {})})

    # ---- data -------------------------------------------------------------------------------
    def add_frames(self, run_id: str, frames: Sequence[GyroFrame]) -> None:
        self.writer(run_id).add_many(frames)

    def last_frame_time(self, run_id: str) -> float | None:
        self.flush(run_id)
        with self.db.session() as s:
            return s.scalar(select(FrameCursor.t_last).where(FrameCursor.run_id == int(run_id)))

    def add_probe_readings(self, run_id: str, t: float, readings: Sequence[ProbeReading]) -> None:
        self.writer(run_id).add_probe_readings(t, readings)

    def add_telemetry(self, run_id: str, t: float, chamber: ChamberStatus | None,
                      turntable: dict[int, AxisState] | None, psu: PsuReading | None) -> None:
        w = self.writer(run_id)
        if chamber is not None:
            w.add_chamber(t, chamber)
        if turntable:
            w.add_turntable(t, turntable)
        if psu is not None:
            w.add_psu(t, psu.volts, psu.amps, psu.on)

    def add_segment(self, run_id: str, step_index: int, kind: str, t_from: float, t_to: float,
                    labels: dict[str, Any]) -> None:
        temp = labels.get("temperature_c")
        self.writer(run_id).add_segment(
            SEGMENT_KIND.get(kind, "record"), t_from, t_to, step_index=step_index,
            temperature_c=float(temp) if isinstance(temp, (int, float)) else None,
            orientation=labels.get("position") if isinstance(labels.get("position"), str) else None,
            repetition=int(labels.get("repetition", 0) or 0), labels={**labels, "step_kind": kind})

    def add_gap(self, run_id: str, t_from: float, t_to: float, reason: str) -> None:
        self.writer(run_id).record_gap(t_from, t_to, reason[:64])

    def open_suspension(self, run_id: str, t_from: float, reason: str) -> int:
        with self.db.session() as s:
            return queries.begin_suspension(s, int(run_id), t_from, reason).id

    def close_suspension(self, run_id: str, suspension_id: Any, t_to: float, reason: str) -> None:
        with self.db.session() as s:
            sus = s.get(Suspension, int(suspension_id))
            if sus is None or sus.run_id != int(run_id):
                raise StorageError(f"run {run_id} has no suspension {suspension_id}")
            sus.t_to = t_to
            sus.reason = reason

    def save_fit(self, run_id: str, step_index: int, result: dict[str, Any]) -> None:
        with self.db.session() as s:
            run = queries.get_run(s, int(run_id), for_update=True)
            live = dict(run.live or {})
            live.setdefault("fits", {})[str(step_index)] = result
            run.live = live


# ================================================================================================
# Control and fitting hooks
# ================================================================================================
class DbControl:
    """``bench.engine.Control`` over ``run_requests``: the oldest unconsumed request of the run, marked
    consumed as it is handed over.  The database is asked at most every ``min_interval_s`` wall
    seconds (the engine polls once per tick, which may be many times a second at high speed)."""

    def __init__(self, db: Database, run_id: int, min_interval_s: float = 0.2) -> None:
        self.db = db
        self.run_id = int(run_id)
        self.min_interval_s = min_interval_s
        self._next = 0.0

    def poll(self) -> str | None:
        now = time.monotonic()
        if now < self._next:
            return None
        with self.db.session() as s:
            req = s.scalars(select(RunRequest).where(RunRequest.run_id == self.run_id,
                                                     RunRequest.consumed_at.is_(None))
                            .order_by(RunRequest.id).limit(1)).first()
            if req is None:
                self._next = now + self.min_interval_s
                return None
            took = s.execute(update(RunRequest).where(RunRequest.id == req.id, RunRequest.consumed_at.is_(None))
                             .values(consumed_at=utcnow())).rowcount
            return req.command if took == 1 else None


def run_dataset(db: Database, run_id: int, latitude_deg: float | None = None):
    """The recorded segments of a stored run as a ``bench.fit.base.Dataset`` (1-s means, gyro in
    deg/h, probe temperatures, orientation).  Latitude goes into the metadata only when every row
    has an orientation, so the Earth rate is removed only where it can be."""
    import numpy as np

    from bench.fit.base import Dataset
    from bench.storage.export import export_columns

    cols = export_columns(db, run_id, resolution="second")
    if "segment_kind" in cols and len(cols["time_s"]):
        keep = cols["segment_kind"] != ""
        cols = {k: v[keep] for k, v in cols.items()}
    meta: dict[str, str] = {"run_id": str(run_id)}
    orient = cols.get("orientation")
    if latitude_deg is not None and orient is not None and len(orient) and bool(np.all(orient != "")):
        meta["latitude_deg"] = repr(float(latitude_deg))
    return Dataset(dict(cols), meta)


def make_fit_hook(db: Database, store: SqlRunStore, *, latitude_deg: float | None, accept: bool = True):
    """Engine fit hook: fit each model of the ``Fit`` step on the run's recorded data, per gyro channel,
    and store the results as the next version of each model for the run's gyro (accepted when
    ``accept``: the newest fit from a completed procedure becomes the gyro's coefficients)."""

    def hook(run_id: str, index: int, step, _store) -> dict[str, Any]:
        from bench.fit.catalog import fit_model

        store.flush(run_id)
        rid = int(run_id)
        with db.session() as s:
            gyro_id = queries.get_run(s, rid).gyro_id
        if gyro_id is None:
            return {"status": "skipped", "reason": "run has no gyro id"}
        ds = run_dataset(db, rid, latitude_deg)
        if len(ds) < 10:
            raise BenchError(f"run {rid}: only {len(ds)} recorded seconds stored; too few to fit")
        results, errors = [], {}
        for model in step.models:
            for ch in ds.gyro_channels():
                try:
                    results.append(fit_model(model, ds, ch))
                except (BenchError, ValueError, KeyError, ArithmeticError) as exc:
                    errors[f"{model}/{ch}"] = f"{type(exc).__name__}: {exc}"
        if not results:
            raise BenchError(f"run {rid}: no model could be fitted: {errors}")
        with db.session() as s:
            versions = queries.save_fits(s, gyro_id, [rid], results, accepted=accept)
        return {"status": "done", "gyro_id": gyro_id, "versions": versions, "accepted": accept,
                "channels": sorted({r.channel for r in results}), "errors": errors}

    return hook


# ================================================================================================
# The worker
# ================================================================================================
def _as_utc(value: dt.datetime | None) -> dt.datetime | None:
    if value is not None and value.tzinfo is None:        # SQLite hands back naive datetimes
        return value.replace(tzinfo=dt.timezone.utc)
    return value


def default_worker_id(bench_name: str) -> str:
    return f"{bench_name}@{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


class Worker:
    """Serves one bench: ``run_forever()`` claims and executes runs until ``stop()``.

    ``devices_factory(config) -> Devices`` opens the drivers for a run (closed after it);
    ``clock`` is the bench clock shared with the devices (a simulated bench's accelerated clock).
    ``heartbeat_s`` / ``stale_after_s`` are wall seconds: a run or bench lease whose heartbeat is older
    than ``stale_after_s`` belongs to a dead worker.
    """

    def __init__(self, db: Database, bench_name: str, config: BenchConfig, devices_factory: DevicesFactory,
                 clock: Clock, *, engine_config: EngineConfig | None = None, worker_id: str | None = None,
                 heartbeat_s: float = 2.0, stale_after_s: float = 15.0, poll_s: float = 0.5,
                 accept_fits: bool = True, writer_options: dict[str, Any] | None = None) -> None:
        if stale_after_s <= 2 * heartbeat_s:
            raise ValueError(f"stale_after_s ({stale_after_s}) must exceed twice heartbeat_s ({heartbeat_s})")
        self.db = db
        self.bench_name = bench_name
        self.config = config
        self.devices_factory = devices_factory
        self.clock = clock
        self.engine_config = engine_config
        self.worker_id = worker_id or default_worker_id(bench_name)
        self.heartbeat_s = heartbeat_s
        self.stale_after_s = stale_after_s
        self.poll_s = poll_s
        self.accept_fits = accept_fits
        self.writer_options = writer_options
        self._stop = threading.Event()
        self.current_run: int | None = None
        self.engine: Engine | None = None
        self.runs_done: list[tuple[int, str]] = []
        with db.session() as s:
            queries.ensure_bench(s, bench_name, _config_doc(config))

    # ---- lifecycle ----------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop claiming new runs (the current run, if any, goes on to its end)."""
        self._stop.set()

    def run_forever(self) -> None:
        log.info("worker %s serving bench %s", self.worker_id, self.bench_name)
        try:
            while not self._stop.is_set():
                try:
                    did = self.run_once()
                except StorageError as exc:
                    log.warning("worker %s: database problem: %s", self.worker_id, exc)
                    did = None
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
            took = s.execute(update(Bench).where(
                Bench.id == bench.id,
                (Bench.worker.is_(None)) | (Bench.worker == self.worker_id) | (Bench.heartbeat_at.is_(None))
                | (Bench.heartbeat_at < limit)).values(worker=self.worker_id, heartbeat_at=now)).rowcount
            if took != 1:
                return None
            active = s.scalars(select(Run).where(Run.bench_id == bench.id, Run.status.in_(ACTIVE))
                               .order_by(Run.id)).all()
            for run in active:
                if run.worker != self.worker_id and _as_utc(run.heartbeat_at) is not None \
                        and _as_utc(run.heartbeat_at) >= limit:
                    return None        # another worker's run is alive: one run per bench
            for run in active:
                got = s.execute(update(Run).where(
                    Run.id == run.id, Run.status.in_(ACTIVE),
                    (Run.heartbeat_at.is_(None)) | (Run.heartbeat_at < limit) | (Run.worker == self.worker_id))
                    .values(worker=self.worker_id, heartbeat_at=now)).rowcount
                if got == 1:
                    queries.add_event(s, run.id, "worker_takeover",
                                      f"worker {self.worker_id} takes over run {run.id} from "
                                      f"{run.worker or 'nobody'} (heartbeat stale) and resumes it",
                                      data={"previous_worker": run.worker})
                    return run.id, True
            stmt = (select(Run.id).where(Run.bench_id == bench.id, Run.status == "queued",
                                         (Run.start_at.is_(None)) | (Run.start_at <= now))
                    .order_by(Run.start_at.is_not(None), Run.start_at, Run.id).limit(1))
            if s.get_bind().dialect.name == "postgresql":
                stmt = stmt.with_for_update(skip_locked=True)
            run_id = s.scalars(stmt).first()
            if run_id is None:
                return None
            got = s.execute(update(Run).where(Run.id == run_id, Run.status == "queued")
                            .values(status="running", worker=self.worker_id, heartbeat_at=now, started_at=now,
                                    config_snapshot=_config_doc(self.config))).rowcount
            if got != 1:
                return None
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
        store = SqlRunStore(self.db, frame_kind=self.config.gyro.frame, nominal_rate_hz=self.config.gyro.data_rate_hz,
                            writer_options=self.writer_options)
        self.current_run = run_id
        stop_beat = threading.Event()
        beat = threading.Thread(target=self._heartbeat_loop, args=(run_id, stop_beat), daemon=True,
                                name=f"heartbeat-run{run_id}")
        devices = None
        status = "failed"
        try:
            devices = self.devices_factory(self.config)
            engine = Engine(devices, store, self.clock, self.config, DbControl(self.db, run_id), self.engine_config,
                            make_fit_hook(self.db, store, latitude_deg=self.config.latitude_deg, accept=self.accept_fits))
            self.engine = engine
            beat.start()
            if resume and has_checkpoint:
                status = engine.resume(str(run_id))
            else:
                module = procedures.get(procedure)
                plan = module.build(module.Params.model_validate(params))
                status = engine.run(str(run_id), plan)
        except BenchError as exc:     # before the engine took over (devices, plan): the run fails here
            status = "failed"
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
                _close_devices(devices)
            self._publish(run_id)
            self.engine = None
            self.current_run = None
        self.runs_done.append((run_id, status))
        return status

    def _fail(self, run_id: int, reason: str) -> None:
        with self.db.session() as s:
            run = queries.get_run(s, run_id, for_update=True)
            if run.status not in TERMINAL:
                run.status, run.finished_at, run.error = "failed", utcnow(), reason
                queries.add_event(s, run_id, "run_failed", reason)

    # ---- heartbeat ----------------------------------------------------------------------------
    def _heartbeat_loop(self, run_id: int, stop: threading.Event) -> None:
        while not stop.wait(self.heartbeat_s):
            try:
                self._publish(run_id)
            except StorageError as exc:
                log.warning("run %s heartbeat: %s", run_id, exc)
            except Exception as exc:  # noqa: BLE001 - a heartbeat problem must not kill the thread
                log.warning("run %s heartbeat failed: %s: %s", run_id, type(exc).__name__, exc)

    def _publish(self, run_id: int) -> None:
        """Heartbeat the run and the bench lease and publish the engine's progress."""
        engine = self.engine
        progress = None
        if engine is not None and engine.plan is not None:
            try:
                progress = engine.progress()
            except Exception:  # noqa: BLE001 - progress is advisory; the engine may be between steps
                progress = None
        now = utcnow()
        with self.db.session() as s:
            run = queries.get_run(s, run_id, for_update=True)
            if run.worker == self.worker_id:
                run.heartbeat_at = now
            if progress is not None and run.status not in TERMINAL:
                speed = getattr(self.clock, "speed", 1.0)
                remaining = float(progress.get("remaining_bench_s") or 0.0)
                wall_left = remaining / speed if speed and speed != float("inf") else 0.0
                live = dict(run.live or {})
                live["progress"] = progress
                live["eta_utc"] = (now + dt.timedelta(seconds=wall_left)).isoformat()
                live["bench_speed"] = speed if speed != float("inf") else None
                live["updated_utc"] = now.isoformat()
                run.live = live
                run.progress = min(1.0, max(0.0, float(progress.get("percent", 0.0)) / 100.0))
                run.current_step = int(progress.get("step_index", 0))
            s.execute(update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                      .values(heartbeat_at=now, state={"state": "busy", "run_id": run_id,
                                                       "worker": self.worker_id}))

    def _bench_state(self, state: dict[str, Any]) -> None:
        with self.db.session() as s:
            s.execute(update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                      .values(heartbeat_at=utcnow(), state={**state, "worker": self.worker_id}))

    def _release_lease(self) -> None:
        try:
            with self.db.session() as s:
                s.execute(update(Bench).where(Bench.name == self.bench_name, Bench.worker == self.worker_id)
                          .values(worker=None, heartbeat_at=None, state={"state": "offline"}))
        except StorageError as exc:
            log.warning("worker %s: could not release the bench lease: %s", self.worker_id, exc)


def _config_doc(config: BenchConfig) -> dict[str, Any]:
    import json
    return json.loads(config.model_dump_json())


def _close_devices(devices: Devices) -> None:
    for name in ("chamber", "turntable", "psu"):
        dev = getattr(devices, name, None)
        try:
            if dev is not None and hasattr(dev, "close"):
                dev.close()
        except Exception as exc:  # noqa: BLE001 - closing must reach every device
            log.warning("closing %s failed: %s", name, exc)
    try:
        devices.gyro.stop()
    except Exception as exc:  # noqa: BLE001
        log.warning("stopping the gyro link failed: %s", exc)


def resolve_devices_factory() -> DevicesFactory:
    """The function that opens the real drivers from a ``BenchConfig`` (the same drivers talk to the
    simulated bench).  Looked up where the integrator provides it."""
    import importlib

    for module, name in (("bench.engine.devices", "open_devices"), ("bench.engine.devices", "build_devices"),
                         ("bench.devices", "open_devices"), ("bench.devices", "build_devices"),
                         ("bench.devices.factory", "open_devices"), ("bench.devices.factory", "build_devices")):
        try:
            fn = getattr(importlib.import_module(module), name, None)
        except ModuleNotFoundError:
            continue
        if callable(fn):
            return fn
    raise BenchError("no device factory available: expected open_devices(config) in bench.engine.devices")

"""``SqlRunStore``: the engine's ``RunStore`` over the runs database (``bench.storage``).

Run ids: the engine's run id is the decimal text of ``runs.id``.  The run row exists before the
engine starts (``new_run`` here, the API, or a worker creates it ``queued``); ``create_run`` attaches
the plan: ``runs.live["plan"]`` / ``["summary"]`` / ``["started_t"]`` and one ``steps`` row per plan
step (named by the step's description).  The same layout as ``bench.worker``'s adapter, so a run
started by ``bench run`` can be resumed by a worker and the other way round.

Status mapping: storage knows queued, running, paused, stopping, suspended, completed, aborted,
failed.  The engine's final ``stopped`` (ended early on an operator stop, after finishing the
current recording) is stored as ``completed`` with ``runs.live["outcome"] = "stopped"`` (and
``live["engine_status"]`` always holds the engine's own word).  A repeated status (``running`` again
on resume) is not a transition and is skipped; the engine is the authority on a run it executes,
so any change is written except leaving a final status (``InvalidTransition``).

Data path: frames, probe readings, telemetry, events, segments and gaps go through one batched
``FrameWriter`` per run (crash-safe per-run frame indexes, buffering through database outages);
steps, status, checkpoints and suspensions are written at once in their own transactions.
Events carry the engine's level in ``data["level"]`` (storage events have no level column).

Segments: engine kinds map to storage kinds (``wait_stable`` -> ``settle``); labels ``position`` ->
``orientation``, ``temperature_c``, ``repetition``; the full engine labels (with ``piece`` /
``complete``) stay in ``segments.labels``.  ``outer_deg`` / ``inner_deg`` come from the last turntable
telemetry; when the labels name no position and the table was at rest, the orientation code is the
one the table angles realise (``bench.devices.orientation.code_at`` with the bench's geometry), so a
run recorded "as mounted" (``thermal_ramp`` default) still says where its axes pointed.

Checkpoint progress: the engine's ``progress.percent`` is stored as ``runs.progress`` (0..1) and
``runs.current_step``; ``live["progress"]`` keeps the engine's whole progress document (each checkpoint
writes both from its instant; between checkpoints the worker's publish refreshes them).
"""
from __future__ import annotations

from bench.jsonsafe import jsonable  # noqa: F401  (re-exported: callers use sqlstore.jsonable)

import os
import socket
import threading
from typing import Any, Sequence

from sqlalchemy import select, update

from bench.config import TurntableGeometry
from bench.engine.outcomes import RunOutcome, StepOutcome
from bench.engine.store import PsuReading
from bench.interfaces import AxisState, ChamberStatus, GyroFrame, ProbeReading
from bench.storage import FrameWriter, queries
from bench.storage.db import Database
from bench.storage.errors import InvalidTransition, StorageError, UnknownRun
from bench.storage.models import FrameCursor, Run, RunStatus, Step, Suspension, utcnow

STORED_FINAL = tuple(sorted(queries.TERMINAL))
SEGMENT_KIND = {"record": "record", "soak": "soak", "ramp": "ramp", "wait_stable": "settle",
                "orient": "move", "table_rate": "record"}
AT_REST_DPS = 0.1
CODE_MATCH_DEG = 1.0


def run_key(run_id: str | int) -> int:
    try:
        return int(run_id)
    except (TypeError, ValueError):
        raise UnknownRun(f"run id {run_id!r} is not a runs.id (an integer)") from None


def process_name() -> str:
    """``cli@host:pid``: identifies the process executing a run (heartbeat owner)."""
    return f"cli@{socket.gethostname()}:{os.getpid()}"


def new_run(db: Database, *, procedure: str, parameters: dict[str, Any], config_snapshot: dict[str, Any],
            gyro_id: str | None, bench_name: str | None, operator: str = "",
            launch: dict[str, Any] | None = None, units: list[tuple[str, str]] | None = None) -> int:
    """A ``queued`` run row (gyro and bench rows made if missing); ``launch`` (how it was started:
    simulated bench settings, engine config) goes to ``runs.live``.  ``units`` (slot, gyro id): a
    multi-gyro run (``gyro_id`` None), one child run per gyro.  Returns ``runs.id``."""
    with db.session() as s:
        run = queries.create_run(s, procedure=procedure, parameters=jsonable(parameters),
                                 config_snapshot=jsonable(config_snapshot), operator=operator, gyro_id=gyro_id,
                                 bench_name=bench_name, units=units)
        if launch:
            run.live = jsonable(dict(launch))
        s.flush()
        return int(run.id)


class SqlRunStore:
    """``bench.engine.RunStore`` over ``bench.storage`` (see the module docstring).

    ``geometry``: the bench's turntable geometry (orientation codes of segments from the table
    angles; None = only labelled positions are stored).  ``frame_kind`` / ``nominal_rate_hz`` /
    ``writer_options`` configure the ``FrameWriter``s.  ``close(run_id)`` flushes and stops a run's
    writer (call it when the engine returns); ``abandon`` drops what is buffered (tests of crashes).
    """

    def __init__(self, db: Database, *, geometry: TurntableGeometry | None = None, frame_kind: str = "kvh_a",
                 nominal_rate_hz: float | None = None, writer_options: dict[str, Any] | None = None) -> None:
        self.db = db
        self.geometry = geometry
        self.frame_kind = frame_kind
        self.nominal_rate_hz = nominal_rate_hz
        self.writer_options = dict(writer_options or {})
        self._writers: dict[int, FrameWriter] = {}
        self._formats: dict[int, dict[str, Any]] = {}     # per-run frame kind / rate (multi-gyro units)
        self._table: dict[int, dict[int, AxisState]] = {}
        # the last table angles looked up as an orientation code and the answer: every unit of a
        # multi-gyro run stores the same table telemetry, so its segments ask for the same angles
        self._orientation_memo: tuple[Any, tuple[str | None, float, float]] | None = None
        self._lock = threading.Lock()
        # ``runs.live`` is one JSON document edited read-modify-write by the engine (status, plan, fits)
        # and by the heartbeat thread (progress): one edit at a time in this process, or a heartbeat that
        # read the document before the final status and wrote after it erases the run's outcome.
        # (PostgreSQL also locks the row across processes: ``_owned`` reads it FOR UPDATE.)
        self._live_lock = threading.Lock()
        # the executing worker's lease (bench.engine.lease.RunLease), set by the worker: every owner write
        # below checks, in its own transaction with the run row locked, that the row still names it
        self.lease = None

    def _owned(self, s, rid: int):
        """The run row, locked; ``LeaseLost`` if a lease is set and the row names another worker."""
        run = queries.get_run(s, rid, for_update=True)
        if self.lease is not None:
            self.lease.check_row(run)
        return run

    def _check_owned(self, s, rid: int) -> None:
        """``_owned`` for a write that does not need the row object: the row locked, only its worker read
        (a checkpoint every two bench minutes would otherwise decode the last checkpoint each time)."""
        worker = queries.run_worker(s, rid, for_update=True)
        if self.lease is not None:
            self.lease.check_worker(worker)

    # ---- writers ----------------------------------------------------------------------------
    def writer(self, run_id: str | int) -> FrameWriter:
        rid = run_key(run_id)
        w = self._writers.get(rid)          # made once per run: found without the lock every later time
        if w is not None:
            return w
        with self._lock:
            w = self._writers.get(rid)
            if w is None:
                opts: dict[str, Any] = {"frame_kind": self.frame_kind, "nominal_rate_hz": self.nominal_rate_hz,
                                        **self._formats.get(rid, {})}
                if opts["frame_kind"] != "kvh_a":
                    opts["valid_status"] = None
                opts.update(self.writer_options)
                w = self._writers[rid] = FrameWriter(self.db, rid, **opts)
            return w

    def set_format(self, run_id: str | int, frame_kind: str, nominal_rate_hz: float | None) -> None:
        """The frame kind and rate of ``run_id``'s gyro (a unit of a multi-gyro run), before its first frame."""
        self._formats[run_key(run_id)] = {"frame_kind": frame_kind, "nominal_rate_hz": nominal_rate_hz}

    def unit_runs(self, run_id: str | int) -> dict[str, str]:
        with self.db.session() as s:
            return {str(u.slot): str(u.id) for u in queries.unit_runs(s, run_key(run_id))}

    def flush(self, run_id: str | int, timeout: float = 60.0) -> None:
        w = self._writers.get(run_key(run_id))
        if w is not None:
            w.flush(timeout)

    def close(self, run_id: str | int, timeout: float = 60.0) -> None:
        """Flush and stop the run's writer (and its gyro units' writers, for a multi-gyro run)."""
        rid = run_key(run_id)
        with self._lock:
            open_units = [r for r in self._writers if r != rid]
        rids = [int(u) for u in self.unit_runs(rid).values() if int(u) in open_units] if open_units else []
        for key in (*rids, rid):
            with self._lock:
                w = self._writers.pop(key, None)
            if w is not None:
                w.close(timeout)

    def abandon(self, run_id: str | int) -> int:
        with self._lock:
            w = self._writers.pop(run_key(run_id), None)
        return w.abandon() if w is not None else 0

    # ---- run --------------------------------------------------------------------------------
    def create_run(self, run_id: str, plan: dict[str, Any], summary: dict[str, Any], t: float) -> None:
        rid = run_key(run_id)
        with self._live_lock, self.db.session() as s:
            run = self._owned(s, rid)
            if run.checkpoint is not None:
                raise StorageError(f"run {rid} has already started (status {run.status}); resume it instead")
            # a run taken over before its first checkpoint starts again, whatever active state its
            # previous worker had left (e.g. suspended on a chamber alarm from its first reading)
            if run.status != RunStatus.QUEUED.value and run.status not in queries.ACTIVE:
                raise InvalidTransition(f"run {rid} is {run.status!r}; only a queued or active run can start")
            live = dict(run.live or {})
            live.update(plan=plan, summary=summary, started_t=t)
            run.live = jsonable(live)
            if s.scalar(select(Step.id).where(Step.run_id == rid).limit(1)) is None:
                described = {st["index"]: st.get("describe", "") for st in summary.get("steps", [])}
                queries.add_steps(s, rid, [{"name": (described.get(i) or st.get("kind", "step"))[:128],
                                            "kind": st.get("kind", "step"), "params": jsonable(st)}
                                           for i, st in enumerate(plan.get("steps", []))])

    def load_plan(self, run_id: str) -> dict[str, Any]:
        with self.db.session() as s:
            plan = (queries.get_run(s, run_key(run_id)).live or {}).get("plan")
        if plan is None:
            raise StorageError(f"run {run_id}: no plan stored (the run never started)")
        return plan

    def set_run_status(self, run_id: str, status: str, t: float, reason: str | None = None) -> None:
        rid = run_key(run_id)
        stored = RunStatus.COMPLETED.value if status == RunOutcome.STOPPED else str(status)
        with self._live_lock, self.db.session() as s:
            run = self._owned(s, rid)
            live = dict(run.live or {})
            if stored == run.status and live.get("engine_status") == status:
                return
            if run.status in STORED_FINAL and stored != run.status:
                raise InvalidTransition(f"run {rid} already ended ({run.status}); cannot become {status!r}")
            queries.stamp_run_status(run, stored, utcnow())
            if stored in STORED_FINAL:
                if status != RunOutcome.COMPLETED and reason:
                    run.error = reason
                live["outcome"] = str(status)
            live.update(engine_status=str(status), status_t=t, status_reason=reason)
            run.live = jsonable(live)

    def heartbeat(self, run_id: str | int, owner: str, progress: dict[str, Any] | None = None) -> None:
        """Mark ``owner`` as the live executor of the run (and refresh ``live["progress"]``)."""
        rid = run_key(run_id)
        with self._live_lock, self.db.session() as s:
            run = self._owned(s, rid)
            run.worker = owner
            run.heartbeat_at = utcnow()
            queries.own_units(s, rid, owner, run.heartbeat_at)
            if progress is not None:
                run.live = jsonable({**(run.live or {}), "progress": progress})

    def save_checkpoint(self, run_id: str, checkpoint: dict[str, Any]) -> None:
        rid = run_key(run_id)
        progress = checkpoint.get("progress") or {}
        percent = progress.get("percent")
        doc = jsonable(checkpoint)
        with self._live_lock, self.db.session() as s:
            self._check_owned(s, rid)
            # the run's percent and its elapsed / remaining bench time in live["progress"] come from one
            # instant: the checkpoint's (the run's last one is taken as it ends); the database sets that
            # one entry of live in the same statement, without the document passing through here
            queries.save_checkpoint(s, rid, doc, current_step=int(checkpoint.get("step_index", 0)),
                                    progress=None if percent is None else min(1.0, max(0.0, percent / 100.0)),
                                    live_entry=("progress", doc["progress"]) if progress else None)

    def load_checkpoint(self, run_id: str) -> dict[str, Any] | None:
        with self.db.session() as s:
            return queries.get_run(s, run_key(run_id)).checkpoint

    def set_step_status(self, run_id: str, index: int, kind: str, status: str, t: float,
                        info: dict[str, Any] | None = None) -> None:
        rid = run_key(run_id)
        with self.db.session() as s:
            self._check_owned(s, rid)
            step = s.scalars(select(Step).where(Step.run_id == rid, Step.index == index)).first()
            if step is None:
                raise StorageError(f"run {rid} has no step {index} ({kind})")
            step.status = str(status)
            if status == StepOutcome.RUNNING:
                step.started_t = t
                step.finished_t = None
            else:
                step.finished_t = t
            if info:
                step.params = jsonable({**(step.params or {}), "info": info})

    def add_event(self, run_id: str, t: float, level: str, kind: str, message: str,
                  data: dict[str, Any] | None = None) -> None:
        if self.lease is not None:          # events go out with the writer's batches (fenced by its token)
            self.lease.check()
        self.writer(run_id).add_event(kind[:32], message, t_bench=t, data=jsonable({"level": level, **(data or {})}))

    # ---- data -------------------------------------------------------------------------------
    def add_frames(self, run_id: str, frames: Sequence[GyroFrame]) -> None:
        self.writer(run_id).add_many(frames)

    def last_frame_time(self, run_id: str) -> float | None:
        rid = run_key(run_id)
        self.flush(rid)
        with self.db.session() as s:
            return s.scalar(select(FrameCursor.t_last).where(FrameCursor.run_id == rid))

    def add_probe_readings(self, run_id: str, t: float, readings: Sequence[ProbeReading]) -> None:
        self.writer(run_id).add_probe_readings(t, readings)

    def add_telemetry(self, run_id: str, t: float, chamber: ChamberStatus | None,
                      turntable: dict[int, AxisState] | None, psu: PsuReading | None) -> None:
        w = self.writer(run_id)
        if chamber is not None:
            w.add_chamber(t, chamber)
        if turntable:
            w.add_turntable(t, turntable)
            self._table[run_key(run_id)] = dict(turntable)
        if psu is not None:
            w.add_psu(t, psu.volts, psu.amps, psu.on)

    def _table_orientation(self, rid: int) -> tuple[str | None, float | None, float | None]:
        """(code or None, outer_deg, inner_deg) of the last turntable telemetry."""
        axes = self._table.get(rid)
        if not axes or self.geometry is None:
            return None, None, None
        a = axes.get(self.geometry.outer_axis_number)
        b = axes.get(self.geometry.inner_axis_number)
        if a is None or b is None:
            return None, None, None
        key = (self.geometry, a.position_deg, a.rate_dps, b.position_deg, b.rate_dps)
        memo = self._orientation_memo
        if memo is not None and memo[0][0] is key[0] and memo[0][1:] == key[1:]:
            return memo[1]
        code = None
        if abs(a.rate_dps) < AT_REST_DPS and abs(b.rate_dps) < AT_REST_DPS:
            from bench.devices.orientation import code_at

            nearest, off_deg = code_at(a.position_deg, b.position_deg, self.geometry)
            code = nearest if off_deg <= CODE_MATCH_DEG else None
        result = (code, a.position_deg, b.position_deg)
        self._orientation_memo = (key, result)
        return result

    def add_segment(self, run_id: str, step_index: int, kind: str, t_from: float, t_to: float,
                    labels: dict[str, Any]) -> None:
        rid = run_key(run_id)
        temp = labels.get("temperature_c")
        position = labels.get("position") if isinstance(labels.get("position"), str) else None
        code, outer, inner = self._table_orientation(rid)
        stored_labels = {**labels, "step_kind": kind}
        if position is None and code is not None:
            stored_labels["orientation_from"] = "table angles"
        rep = labels.get("repetition", 0)
        self.writer(rid).add_segment(
            SEGMENT_KIND.get(kind, "record"), t_from, t_to, step_index=step_index,
            temperature_c=float(temp) if isinstance(temp, (int, float)) and not isinstance(temp, bool) else None,
            orientation=(position.upper() if position else code), outer_deg=outer, inner_deg=inner,
            repetition=int(rep) if isinstance(rep, (int, float)) and not isinstance(rep, bool) else 0,
            labels=jsonable(stored_labels))

    def add_gap(self, run_id: str, t_from: float, t_to: float, reason: str,
                frames_missing: int | None = None) -> None:
        """``frames_missing`` None: the next frame closes the gap and counts them; given (an outage that
        lasted to the end of the run, no next frame): a gap row of its own."""
        self.writer(run_id).record_gap(t_from, max(t_from, t_to), reason[:64], frames_missing)

    def open_suspension(self, run_id: str, t_from: float, reason: str) -> int:
        with self.db.session() as s:
            self._check_owned(s, run_key(run_id))
            sid = int(queries.begin_suspension(s, run_key(run_id), t_from, reason).id)
        self.writer(run_id).begin_suspension(t_from)      # frames lost meanwhile: a suspension gap
        return sid

    def close_suspension(self, run_id: str, suspension_id: Any, t_to: float, reason: str) -> None:
        rid = run_key(run_id)
        with self.db.session() as s:
            self._check_owned(s, rid)
            sus = s.get(Suspension, int(suspension_id))
            if sus is None or sus.run_id != rid:
                raise StorageError(f"run {rid} has no suspension {suspension_id}")
            sus.t_to = t_to
            sus.reason = reason
        self.writer(rid).end_suspension(t_to)

    def save_fit(self, run_id: str, step_index: int, result: dict[str, Any]) -> None:
        with self._live_lock, self.db.session() as s:
            run = self._owned(s, run_key(run_id))
            live = dict(run.live or {})
            fits = dict(live.get("fits") or {})
            fits[str(step_index)] = result
            live["fits"] = fits
            run.live = jsonable(live)


# ---- reading a run back (``bench runs show``) ------------------------------------------------------
def run_report(db: Database, run_id: int) -> dict[str, Any]:
    """Everything ``bench runs show`` prints: status, step, progress, frames, gaps, suspensions..."""
    from bench.storage.models import Segment

    with db.session() as s:
        run = queries.get_run(s, int(run_id))
        live = dict(run.live or {})
        steps = list(s.scalars(select(Step).where(Step.run_id == run.id).order_by(Step.index)))
        gaps = queries.list_gaps(s, run.id)
        suspensions = list(s.scalars(select(Suspension).where(Suspension.run_id == run.id).order_by(Suspension.id)))
        n_segments = len(list(s.scalars(select(Segment.id).where(Segment.run_id == run.id))))
        frames = queries.frame_count(s, run.id)
        n_steps = len(steps)
        current = run.current_step
        cp = run.checkpoint or {}
        progress_doc = cp.get("progress") or live.get("progress") or {}
        doc = {
            "run_id": run.id,
            "procedure": run.procedure,
            "gyro_id": run.gyro_id,
            "status": run.status,
            "outcome": live.get("outcome"),
            "engine_status": live.get("engine_status"),
            "error": run.error,
            "step": current,
            "n_steps": n_steps,
            "step_kind": steps[current].kind if current is not None and current < n_steps else None,
            "step_name": steps[current].name if current is not None and current < n_steps else None,
            "progress": float(run.progress or 0.0),
            "percent": progress_doc.get("percent"),
            "remaining_bench_s": progress_doc.get("remaining_bench_s"),
            "frames": frames,
            # one gap row per outage: their frames and spans add up to what the run lost
            "frames_lost": int(sum(g.frames_missing or 0 for g in gaps)),
            "bench_seconds_lost": float(sum(g.t_to - g.t_from for g in gaps)),
            "segments": n_segments,
            "gaps": [{"t_from": g.t_from, "t_to": g.t_to, "duration_s": g.t_to - g.t_from, "reason": g.reason,
                      "frames_missing": g.frames_missing, "after_index": g.after_index} for g in gaps],
            "suspensions": [{"t_from": x.t_from, "t_to": x.t_to, "reason": x.reason,
                             "duration_s": None if x.t_to is None else x.t_to - x.t_from} for x in suspensions],
            "fits": live.get("fits") or {},
            "parameters": run.parameters,
            "created_at": run.created_at.isoformat() if run.created_at else None,
            "started_at": run.started_at.isoformat() if run.started_at else None,
            "finished_at": run.finished_at.isoformat() if run.finished_at else None,
            "worker": run.worker,
            "sim": live.get("sim"),
            "steps_done": sum(1 for st in steps if st.status == StepOutcome.DONE),
            "status_reason": live.get("status_reason"),
            "parent_id": run.parent_id,
            "slot": run.slot,
            # a multi-gyro run: each gyro's own run (its data, gaps and fits are there)
            "units": [{"slot": u.slot, "run_id": u.id, "gyro_id": u.gyro_id, "status": u.status,
                       "outcome": (u.live or {}).get("outcome"), "error": u.error,
                       "frames": queries.frame_count(s, u.id),
                       "gaps": [{"t_from": g.t_from, "t_to": g.t_to, "reason": g.reason,
                                 "frames_missing": g.frames_missing} for g in queries.list_gaps(s, u.id)]}
                      for u in queries.unit_runs(s, run.id)],
        }
    from bench.storage.sampling import sampling_summary

    doc["sampling"] = sampling_summary(db, run.id)
    return jsonable(doc)


def claim_for_resume(db: Database, run_id: int, owner: str, *, stale_after_s: float = 10.0,
                     force: bool = False) -> None:
    """Take a run over for ``bench resume``: refuse a final run, and a run whose executor still looks
    alive (same host: its pid exists; other host: heartbeat fresher than ``stale_after_s``) unless
    ``force``.  Sets ``runs.worker`` / ``heartbeat_at`` to ``owner``."""
    import datetime as dt

    with db.session() as s:
        run = queries.get_run(s, int(run_id), for_update=True)
        if run.status in STORED_FINAL:
            raise InvalidTransition(f"run {run_id} already ended ({run.status}"
                                    f"{', ' + run.live['outcome'] if run.live and run.live.get('outcome') else ''}); "
                                    f"nothing to resume")
        if run.checkpoint is None:
            raise StorageError(f"run {run_id} has no checkpoint (status {run.status}); it never started, "
                               f"nothing to resume")
        if not force and run.worker and run.worker != owner:
            if _executor_alive(run.worker, run.heartbeat_at, stale_after_s, dt):
                raise StorageError(f"run {run_id} is still being executed by {run.worker} (heartbeat "
                                   f"{run.heartbeat_at}); stop that process first or use --force")
        s.execute(update(Run).where(Run.id == run.id).values(worker=owner, heartbeat_at=utcnow()))
        queries.own_units(s, run.id, owner)


def _executor_alive(worker: str, heartbeat_at, stale_after_s: float, dt) -> bool:
    host = socket.gethostname()
    if worker.startswith("cli@") and ":" in worker:
        w_host, _, pid = worker[4:].rpartition(":")
        if w_host == host and pid.isdigit():
            try:
                os.kill(int(pid), 0)
            except ProcessLookupError:
                return False
            except PermissionError:
                return True
            return True
    if heartbeat_at is None:
        return False
    if heartbeat_at.tzinfo is None:
        heartbeat_at = heartbeat_at.replace(tzinfo=dt.timezone.utc)
    return (utcnow() - heartbeat_at).total_seconds() < stale_after_s

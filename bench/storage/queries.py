"""Run bookkeeping the engine needs: runs and their state machine, steps, events, segments,
suspensions, gaps, gyros, benches and versioned fits.  Every function takes an open ``Session``
(``with db.session() as s: ...``) and leaves committing to the caller's context.
"""
from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from sqlalchemy import String, case, cast, func, literal, select, update
from sqlalchemy.dialects.postgresql import ARRAY, JSONB
from sqlalchemy.orm import Session

from bench.storage.errors import InvalidTransition, StorageError, UnknownRun
from bench.storage.models import (SEGMENT_KINDS, Bench, Event, Fit, Gap, Gyro, Run, RunStatus, Segment, Step,
                                  Suspension, utcnow)

TERMINAL = frozenset({RunStatus.COMPLETED.value, RunStatus.ABORTED.value, RunStatus.FAILED.value})
ACTIVE = frozenset({RunStatus.RUNNING.value, RunStatus.PAUSED.value, RunStatus.STOPPING.value,
                    RunStatus.SUSPENDED.value})      # a worker owns the run
TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "aborted", "failed"}),
    "running": frozenset({"paused", "stopping", "completed", "aborted", "failed", "suspended"}),
    "paused": frozenset({"running", "stopping", "aborted", "failed", "suspended"}),
    "stopping": frozenset({"completed", "aborted", "failed", "suspended"}),
    "suspended": frozenset({"queued", "running", "aborted", "failed"}),
    "completed": frozenset(),
    "aborted": frozenset(),
    "failed": frozenset(),
}


# ---------------------------------------------------------------- gyros and benches
def ensure_gyro(session: Session, gyro_id: str, *, type: str | None = None, notes: str | None = None) -> Gyro:
    gyro = session.get(Gyro, gyro_id)
    if gyro is None:
        gyro = Gyro(gyro_id=gyro_id, type=type or "", notes=notes or "")
        session.add(gyro)
    else:
        if type is not None:
            gyro.type = type
        if notes is not None:
            gyro.notes = notes
    session.flush()
    return gyro


def ensure_bench(session: Session, name: str, config: Mapping[str, Any] | None = None) -> Bench:
    bench = session.scalars(select(Bench).where(Bench.name == name)).first()
    if bench is None:
        bench = Bench(name=name, config=dict(config or {}))
        session.add(bench)
    elif config is not None:
        bench.config = dict(config)
    session.flush()
    return bench


# ---------------------------------------------------------------- runs
def create_run(session: Session, *, procedure: str, parameters: Mapping[str, Any] | None = None,
               config_snapshot: Mapping[str, Any] | None = None, operator: str = "", gyro_id: str | None = None,
               bench_name: str | None = None, start_at: dt.datetime | None = None,
               units: Sequence[tuple[str, str]] | None = None) -> Run:
    """A new ``queued`` run.  The gyro and bench rows are created if missing (bench with the snapshot).

    ``units``: (slot, gyro id) per gyro of a multi-gyro run: the run is then the parent (no gyro of its
    own) and gets one queued child run per gyro (``runs.parent_id`` / ``runs.slot``)."""
    if units is not None:
        if gyro_id is not None:
            raise ValueError("a multi-gyro run names its gyros in units, not gyro_id")
        _check_units(units)
    run = Run(procedure=procedure, parameters=dict(parameters or {}), config_snapshot=dict(config_snapshot or {}),
              operator=operator, status=RunStatus.QUEUED.value, start_at=start_at, progress=0.0)
    if gyro_id is not None:
        run.gyro_id = ensure_gyro(session, gyro_id).gyro_id
    if bench_name is not None:
        run.bench_id = ensure_bench(session, bench_name, config_snapshot if config_snapshot else None).id
    session.add(run)
    session.flush()
    for slot, unit_gyro in units or ():
        session.add(Run(procedure=procedure, parameters=dict(parameters or {}), config_snapshot=run.config_snapshot,
                        operator=operator, status=RunStatus.QUEUED.value, start_at=start_at, progress=0.0,
                        gyro_id=ensure_gyro(session, unit_gyro).gyro_id, bench_id=run.bench_id, parent_id=run.id,
                        slot=slot))
    session.flush()
    return run


def _check_units(units: Sequence[tuple[str, str]]) -> None:
    if not units:
        raise ValueError("a multi-gyro run needs at least one (slot, gyro id)")
    for what, values in (("slot", [u[0] for u in units]), ("gyro id", [u[1] for u in units])):
        seen = set()
        for value in values:
            if value in seen:
                raise ValueError(f"{what} {value!r} is named twice in one run")
            seen.add(value)


def unit_runs(session: Session, run_id: int) -> list[Run]:
    """The child runs of a multi-gyro run, in slot order of creation (empty for a one-gyro run)."""
    return list(session.scalars(select(Run).where(Run.parent_id == run_id).order_by(Run.id)))


def own_units(session: Session, run_id: int, worker: str, now: dt.datetime | None = None) -> None:
    """The worker that claimed (or took over) a multi-gyro run owns its child runs too."""
    session.execute(update(Run).where(Run.parent_id == run_id)
                    .values(worker=worker, heartbeat_at=now or utcnow()))


def get_run(session: Session, run_id: int, *, for_update: bool = False) -> Run:
    stmt = select(Run).where(Run.id == run_id)
    if for_update and session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update()
    run = session.scalars(stmt).first()
    if run is None:
        raise UnknownRun(f"run {run_id} does not exist")
    return run


def run_worker(session: Session, run_id: int, *, for_update: bool = False) -> str | None:
    """The run's ``worker`` column alone (its JSON columns are not read), the row locked if asked."""
    stmt = select(Run.worker).where(Run.id == run_id)
    if for_update and session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update()
    row = session.execute(stmt).first()
    if row is None:
        raise UnknownRun(f"run {run_id} does not exist")
    return row[0]


def list_runs(session: Session, *, status: str | Iterable[str] | None = None, limit: int | None = None) -> list[Run]:
    stmt = select(Run).order_by(Run.id.desc())
    if status is not None:
        stmt = stmt.where(Run.status.in_([status] if isinstance(status, str) else list(status)))
    if limit is not None:
        stmt = stmt.limit(limit)
    return list(session.scalars(stmt))


def stamp_run_status(run: Run, new: str, now: dt.datetime) -> None:
    """Set ``run.status`` to ``new`` (no transition check) and stamp ``started_at`` on the first
    ``running`` and ``finished_at`` on a terminal status."""
    run.status = new
    if new == RunStatus.RUNNING.value and run.started_at is None:
        run.started_at = now
    if new in TERMINAL:
        run.finished_at = now


def set_run_status(session: Session, run_id: int, status: str | RunStatus, *, error: str | None = None,
                   worker: str | None = None) -> Run:
    """Move a run through the state machine ``TRANSITIONS``; stamps ``started_at`` on the first
    ``running`` and ``finished_at`` on a terminal status.  Raises ``InvalidTransition``."""
    new = RunStatus(status).value
    run = get_run(session, run_id, for_update=True)
    if new != run.status and new not in TRANSITIONS[run.status]:
        raise InvalidTransition(f"run {run_id}: cannot go from {run.status!r} to {new!r} "
                                f"(allowed: {', '.join(sorted(TRANSITIONS[run.status])) or 'none, it is final'})")
    now = utcnow()
    stamp_run_status(run, new, now)
    if error is not None:
        run.error = error
    if worker is not None:
        run.worker = worker
        run.heartbeat_at = now
    session.flush()
    return run


def claim_next_run(session: Session, worker: str, *, bench_id: int | None = None,
                   now: dt.datetime | None = None, **values: Any) -> Run | None:
    """Take the next due ``queued`` run (of bench ``bench_id`` when given) and mark it ``running`` for
    ``worker`` (``values``: more columns to set, e.g. ``config_snapshot``).  The one claim order:
    scheduled runs whose ``start_at`` has come, earliest ``start_at`` first; then unscheduled runs in
    order of creation.  PostgreSQL: ``FOR UPDATE SKIP LOCKED`` so two workers never claim the same
    run; SQLite serialises writers anyway (the status is re-checked in the UPDATE)."""
    now = now or utcnow()
    # a multi-gyro run's child runs are executed with their parent, never on their own
    where = [Run.status == RunStatus.QUEUED.value, (Run.start_at.is_(None)) | (Run.start_at <= now),
             Run.parent_id.is_(None)]
    if bench_id is not None:
        where.append(Run.bench_id == bench_id)
    stmt = select(Run.id).where(*where).order_by(Run.start_at.is_(None), Run.start_at, Run.id).limit(1)
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(skip_locked=True)
    run_id = session.scalars(stmt).first()
    if run_id is None:
        return None
    res = session.execute(update(Run).where(Run.id == run_id, Run.status == RunStatus.QUEUED.value)
                          .values(status=RunStatus.RUNNING.value, worker=worker, heartbeat_at=now,
                                  started_at=func.coalesce(Run.started_at, now), **values))
    if res.rowcount != 1:
        return None
    own_units(session, run_id, worker, now)
    session.flush()
    run = session.get(Run, run_id)
    session.refresh(run)
    return run


def heartbeat(session: Session, run_id: int, worker: str) -> None:
    """Record that ``worker`` is alive and still owns the run; raises if another worker owns it."""
    res = session.execute(update(Run).where(Run.id == run_id, Run.worker == worker)
                          .values(heartbeat_at=utcnow()))
    if res.rowcount != 1:
        raise StorageError(f"run {run_id} is not owned by worker {worker!r}")


def stale_runs(session: Session, older_than: dt.timedelta) -> list[Run]:
    """Runs marked running/paused/stopping whose worker heartbeat is older than ``older_than``."""
    limit = utcnow() - older_than
    return list(session.scalars(select(Run).where(Run.status.in_(["running", "paused", "stopping"]),
                                                  Run.parent_id.is_(None),
                                                  (Run.heartbeat_at.is_(None)) | (Run.heartbeat_at < limit))))


def live_with(session: Session, key: str, value: Any) -> Any:
    """SQL for the run's ``live`` document with ``key`` set to ``value`` (plain JSON), the other entries
    as they are: the database edits the document in place, so the engine does not read, decode and
    encode the whole of it (the plan and its summary, tens of kB) to change one entry."""
    text = json.dumps(value, allow_nan=False, separators=(",", ":"))
    if session.get_bind().dialect.name == "postgresql":
        doc = case((func.jsonb_typeof(Run.live) == "object", Run.live), else_=cast(literal("{}", String), JSONB))
        return func.jsonb_set(doc, literal([key], ARRAY(String)), cast(literal(text, String), JSONB))
    doc = case((func.json_type(Run.live) == "object", Run.live), else_=literal("{}"))   # SQL NULL or JSON null: {}
    return func.json_set(doc, f"$.{key}", func.json(text))


def save_checkpoint(session: Session, run_id: int, checkpoint: Mapping[str, Any], *,
                    current_step: int | None = None, progress: float | None = None,
                    live_entry: tuple[str, Any] | None = None) -> None:
    """Store the run's checkpoint (and ``current_step`` / ``progress`` 0..1); ``live_entry``: a
    ``(key, value)`` set in the run's ``live`` document by the same statement (``live_with``)."""
    values: dict[str, Any] = {"checkpoint": dict(checkpoint)}
    if current_step is not None:
        values["current_step"] = current_step
    if progress is not None:
        if not 0.0 <= progress <= 1.0:
            raise ValueError(f"progress must be within 0..1, got {progress}")
        values["progress"] = progress
    if live_entry is not None:
        values["live"] = live_with(session, *live_entry)
    if session.execute(update(Run).where(Run.id == run_id).values(**values)).rowcount != 1:
        raise UnknownRun(f"run {run_id} does not exist")


# ---------------------------------------------------------------- steps and events
def add_steps(session: Session, run_id: int, steps: Sequence[Mapping[str, Any]]) -> list[Step]:
    """Create the run's plan: each mapping has ``name``, ``kind`` and optional ``params``; indexes 0..n-1
    follow any existing steps."""
    start = session.scalar(select(func.count()).select_from(Step).where(Step.run_id == run_id)) or 0
    rows = [Step(run_id=run_id, index=start + i, name=s["name"], kind=s["kind"], params=dict(s.get("params", {})))
            for i, s in enumerate(steps)]
    session.add_all(rows)
    session.flush()
    return rows


def set_step_status(session: Session, run_id: int, index: int, status: str, *, t_bench: float | None = None) -> Step:
    step = session.scalars(select(Step).where(Step.run_id == run_id, Step.index == index)).first()
    if step is None:
        raise StorageError(f"run {run_id} has no step {index}")
    step.status = status
    if status == "running" and t_bench is not None:
        step.started_t = t_bench
    elif status in ("done", "completed", "failed", "skipped", "aborted") and t_bench is not None:
        step.finished_t = t_bench
    session.flush()
    return step


def add_event(session: Session, run_id: int, kind: str, message: str, *, t_bench: float | None = None,
              data: Mapping[str, Any] | None = None) -> Event:
    ev = Event(run_id=run_id, kind=kind, message=message, t_bench=t_bench, data=dict(data) if data else None,
               wall_time=utcnow())
    session.add(ev)
    session.flush()
    return ev


def list_events(session: Session, run_id: int, *, after_id: int = 0, limit: int | None = None) -> list[Event]:
    stmt = select(Event).where(Event.run_id == run_id, Event.id > after_id).order_by(Event.id)
    if limit is not None:
        stmt = stmt.limit(limit)
    return list(session.scalars(stmt))


# ---------------------------------------------------------------- segments, suspensions, gaps
def open_segment(session: Session, run_id: int, kind: str, t_start: float, **labels: Any) -> Segment:
    """Start a labelled segment; label keywords: temperature_c, orientation, outer_deg, inner_deg,
    repetition, step_index, labels (dict)."""
    if kind not in SEGMENT_KINDS:
        raise ValueError(f"segment kind {kind!r} is not one of {SEGMENT_KINDS}")
    seg = Segment(run_id=run_id, kind=kind, t_start=t_start, **labels)
    session.add(seg)
    session.flush()
    return seg


def close_segment(session: Session, segment_id: int, t_end: float) -> Segment:
    seg = session.get(Segment, segment_id)
    if seg is None:
        raise StorageError(f"segment {segment_id} does not exist")
    if t_end < seg.t_start:
        raise ValueError(f"segment {segment_id}: t_end {t_end} is before t_start {seg.t_start}")
    seg.t_end = t_end
    session.flush()
    return seg


def list_segments(session: Session, run_id: int) -> list[Segment]:
    return list(session.scalars(select(Segment).where(Segment.run_id == run_id).order_by(Segment.t_start,
                                                                                          Segment.id)))


def begin_suspension(session: Session, run_id: int, t_from: float, reason: str) -> Suspension:
    sus = Suspension(run_id=run_id, t_from=t_from, reason=reason)
    session.add(sus)
    session.flush()
    return sus


def end_suspension(session: Session, run_id: int, t_to: float) -> Suspension | None:
    """Close the run's open suspension (if any)."""
    sus = session.scalars(select(Suspension).where(Suspension.run_id == run_id, Suspension.t_to.is_(None))
                          .order_by(Suspension.id.desc())).first()
    if sus is not None:
        sus.t_to = t_to
        session.flush()
    return sus


def list_gaps(session: Session, run_id: int) -> list[Gap]:
    return list(session.scalars(select(Gap).where(Gap.run_id == run_id).order_by(Gap.t_from, Gap.id)))


def frame_count(session: Session, run_id: int) -> int:
    """Frames stored for the run (from the writer cursor; 0 when none)."""
    from bench.storage.models import FrameCursor
    return int(session.scalar(select(FrameCursor.next_index).where(FrameCursor.run_id == run_id)) or 0)


# ---------------------------------------------------------------- fits
def save_fits(session: Session, gyro_id: str, run_ids: Sequence[int], results: Iterable[Any], *,
              accepted: bool = False) -> dict[str, int]:
    """Store fit results (``bench.fit.base.FitResult`` or dicts with model/channel/coefficients) as the
    next version of each model for the gyro; returns {model: version} (one version per call and
    model, shared by its channels).
    With ``accepted=True`` the new version becomes the accepted one."""
    items = [r.to_json() if hasattr(r, "to_json") else dict(r) for r in results]
    if not items:
        raise ValueError("no fit results to save")
    ensure_gyro(session, gyro_id)
    versions: dict[str, int] = {}
    for item in items:
        model = item["model"]
        if model not in versions:
            current = session.scalar(select(func.max(Fit.version)).where(Fit.gyro_id == gyro_id, Fit.model == model))
            versions[model] = (current or 0) + 1
        session.add(Fit(gyro_id=gyro_id, run_ids=[int(r) for r in run_ids], model=model, channel=item["channel"],
                        version=versions[model], coefficients=dict(item.get("coefficients", {})), result=item,
                        accepted=False, created_at=utcnow()))
    session.flush()
    if accepted:
        for model, version in versions.items():
            accept_fits(session, gyro_id, model, version)
    return versions


def accept_fits(session: Session, gyro_id: str, model: str, version: int) -> int:
    """Make ``version`` the accepted fit of (gyro, model) - every other version is un-accepted.
    Returns the number of channel rows accepted."""
    rows = session.execute(update(Fit).where(Fit.gyro_id == gyro_id, Fit.model == model,
                                             Fit.version == version).values(accepted=True)).rowcount
    if rows == 0:
        raise StorageError(f"gyro {gyro_id!r} has no {model!r} fit version {version}")
    session.execute(update(Fit).where(Fit.gyro_id == gyro_id, Fit.model == model, Fit.version != version)
                    .values(accepted=False))
    return rows


def list_fits(session: Session, gyro_id: str, *, model: str | None = None, accepted_only: bool = False) -> list[Fit]:
    stmt = select(Fit).where(Fit.gyro_id == gyro_id)
    if model is not None:
        stmt = stmt.where(Fit.model == model)
    if accepted_only:
        stmt = stmt.where(Fit.accepted.is_(True))
    return list(session.scalars(stmt.order_by(Fit.model, Fit.version.desc(), Fit.channel)))

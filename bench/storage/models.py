"""SQLAlchemy 2 models of the runs database (typed ``Mapped[...]`` declarative).

Time conventions
----------------
* ``*_at`` columns (``created_at``, ``started_at``, ``heartbeat_at``, ``start_at``...) are **wall-clock**
  timestamps (timezone-aware UTC): they tell people when something happened.
* ``t``, ``t_*`` and ``*_t`` float columns are **bench time** in seconds (``bench.clock``), the
  axis all measurements share; with an accelerated clock it differs from the wall.

Frame storage (why chunks)
--------------------------
A gyro frame is 36 bytes (KVH Format A) and arrives at up to 1000 Hz.  One row per frame with
decoded float columns would cost 100+ bytes per frame in either database.  Frames are therefore
stored in ``frame_chunks`` rows holding up to ``chunk_frames`` consecutive frames: the raw frames
concatenated exactly as received (bit-exact, re-exportable), a little-endian int32 array of host
time offsets from ``t_first`` in microseconds and a little-endian int16 array of the decoded
temperature in 1/100 degC (the wire unit of the temperature is a device setting, so the decoded
value is kept rather than re-derived).  Decoded rates and accelerations are recomputed from the raw
bytes with numpy (``bench.storage.codec``).  ``frame_seconds`` keeps, per bench second, the sums
needed for 1-s means (packed 16 seconds to a row), written in the same transaction as the chunks,
so the 1-s query never decodes raw frames.
"""
from __future__ import annotations

import datetime as dt
import enum
from typing import Any

from sqlalchemy import (JSON, BigInteger, Boolean, CheckConstraint, DateTime, Float, ForeignKey, Index,
                        Integer, LargeBinary, MetaData, String, Text, UniqueConstraint)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

NAMING = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

JsonType = JSON().with_variant(JSONB(), "postgresql")


class RunStatus(str, enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    STOPPING = "stopping"
    COMPLETED = "completed"
    ABORTED = "aborted"
    FAILED = "failed"
    SUSPENDED = "suspended"


RUN_STATUSES = tuple(s.value for s in RunStatus)
SEGMENT_KINDS = ("soak", "record", "ramp", "settle", "move")
TELEMETRY_DEVICES = ("chamber", "turntable", "psu")


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)
    type_annotation_map = {
        dict[str, Any]: JsonType,
        list[Any]: JsonType,
        dt.datetime: DateTime(timezone=True),
        float: Float(precision=53),
    }


class Gyro(Base):
    __tablename__ = "gyros"

    gyro_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    type: Mapped[str] = mapped_column(String(64), default="")
    notes: Mapped[str] = mapped_column(Text, default="")


class Bench(Base):
    __tablename__ = "benches"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    config: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # operator service (migration 0002_service): the worker serving the bench and its report
    worker: Mapped[str | None] = mapped_column(String(128))
    heartbeat_at: Mapped[dt.datetime | None]
    state: Mapped[dict[str, Any] | None]


class Run(Base):
    __tablename__ = "runs"
    __table_args__ = (
        CheckConstraint(_in("status", RUN_STATUSES), name="status"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress"),
        Index(None, "status", "start_at"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    procedure: Mapped[str] = mapped_column(String(128))
    parameters: Mapped[dict[str, Any]] = mapped_column(default=dict)
    config_snapshot: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[str] = mapped_column(String(16), default=RunStatus.QUEUED.value)
    operator: Mapped[str] = mapped_column(String(64), default="")
    gyro_id: Mapped[str | None] = mapped_column(ForeignKey("gyros.gyro_id"), index=True)
    bench_id: Mapped[int | None] = mapped_column(ForeignKey("benches.id"))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    started_at: Mapped[dt.datetime | None]
    finished_at: Mapped[dt.datetime | None]
    start_at: Mapped[dt.datetime | None]          # scheduled start (queued runs wait until then)
    current_step: Mapped[int | None]
    progress: Mapped[float] = mapped_column(default=0.0)
    checkpoint: Mapped[dict[str, Any] | None]      # engine state needed to resume
    worker: Mapped[str | None] = mapped_column(String(128))
    heartbeat_at: Mapped[dt.datetime | None]
    error: Mapped[str | None] = mapped_column(Text)
    live: Mapped[dict[str, Any] | None]            # progress / ETA refreshed by the worker (0002_service)
    # several gyros in one chamber (0005_gyro_units): the run of one gyro of a multi-gyro run names that
    # run (the parent: plan, steps, status, chamber) and its fixture slot.  No database foreign key: see
    # the migration (SQLite could only add or drop one by rebuilding ``runs``)
    parent_id: Mapped[int | None] = mapped_column(Integer, index=True)
    slot: Mapped[str | None] = mapped_column(String(32))

    gyro: Mapped[Gyro | None] = relationship()
    bench: Mapped[Bench | None] = relationship()
    steps: Mapped[list["Step"]] = relationship(order_by="Step.index", cascade="all, delete-orphan",
                                               passive_deletes=True)


class Step(Base):
    __tablename__ = "steps"
    __table_args__ = (UniqueConstraint("run_id", "index"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    index: Mapped[int]
    name: Mapped[str] = mapped_column(String(128))
    kind: Mapped[str] = mapped_column(String(32))
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[str] = mapped_column(String(16), default="pending")
    started_t: Mapped[float | None]               # bench time
    finished_t: Mapped[float | None]


class Event(Base):
    __tablename__ = "events"
    __table_args__ = (Index(None, "run_id", "t_bench"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    t_bench: Mapped[float | None]
    wall_time: Mapped[dt.datetime] = mapped_column(default=utcnow)
    kind: Mapped[str] = mapped_column(String(32))
    message: Mapped[str] = mapped_column(Text, default="")
    data: Mapped[dict[str, Any] | None]


class FrameCursor(Base):
    """Per-run write position of the frame writer, updated in the same transaction as the chunks.

    ``next_index`` is the index the next frame gets; ``batch_seq`` numbers committed writer
    transactions (so a writer can tell whether a commit whose reply was lost went through);
    ``writer_token`` fences off a stale writer once a new one has taken the run over.
    """

    __tablename__ = "frame_cursors"

    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    next_index: Mapped[int] = mapped_column(BigInteger, default=0)
    batch_seq: Mapped[int] = mapped_column(BigInteger, default=0)
    writer_token: Mapped[str] = mapped_column(String(64))
    t_last: Mapped[float | None]                  # host time of the last stored frame
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class FrameChunk(Base):
    """Up to N consecutive frames of one run: frames ``first_index .. first_index + count - 1``."""

    __tablename__ = "frame_chunks"
    __table_args__ = (UniqueConstraint("run_id", "first_index"),
                      CheckConstraint("count > 0", name="count"))

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    first_index: Mapped[int] = mapped_column(BigInteger)
    count: Mapped[int]
    t_first: Mapped[float]                        # host bench time of the first frame
    t_last: Mapped[float]                         # host bench time of the last frame
    frame_kind: Mapped[str] = mapped_column(String(16))
    frame_size: Mapped[int]
    raw: Mapped[bytes] = mapped_column(LargeBinary)        # count * frame_size bytes, as received
    dt_us: Mapped[bytes] = mapped_column(LargeBinary)      # count x int32 LE: host time - t_first, us
    temp_centi: Mapped[bytes] = mapped_column(LargeBinary)  # count x int16 LE: 1/100 degC, -32768 = none


SECONDS_PER_BLOCK = 16
SUM_FIELDS = ("n", "n_invalid", "sum_dt", "sum_gx", "sum_gy", "sum_gz", "sum_ax", "sum_ay", "sum_az",
              "n_temp", "sum_temp", "sum_fx", "sum_fy", "sum_fz")


class FrameSecond(Base):
    """Per-second sums of a run's frames, packed 16 seconds to a row.

    ``block`` is the first bench second of the row (a multiple of 16); ``sums`` is a little-endian
    float64 array of shape (16, len(SUM_FIELDS)): per second ``[block + i, block + i + 1)`` the
    count of valid-status frames ``n``, of left-out frames ``n_invalid``, the sum of their time
    offsets in the second, of gyro x/y/z, accel x/y/z, the count and sum of device temperatures and
    of frequencies (zero when ``has_freq`` is false).  Means are ``sum / n``.  Packing keeps a 24 h
    run at 5 400 rows (the 1-s means read in milliseconds) and a row at 1.8 kB, inline in
    PostgreSQL (no TOAST) so the writer's updates of the current block stay cheap.
    """

    __tablename__ = "frame_seconds"

    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    block: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    has_freq: Mapped[bool] = mapped_column(Boolean, default=False)
    sums: Mapped[bytes] = mapped_column(LargeBinary)


class ProbeReadingRow(Base):
    __tablename__ = "probe_readings"
    __table_args__ = (Index(None, "run_id", "name", "t"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    t: Mapped[float]
    name: Mapped[str] = mapped_column(String(32))
    serial: Mapped[str] = mapped_column(String(16), default="")
    celsius: Mapped[float | None]
    fault: Mapped[str | None] = mapped_column(String(128))


class Telemetry(Base):
    """One sample of one device.  Typed nullable columns (NULLs cost ~nothing) instead of name/value
    rows: one row per sample, and export reads whole columns."""

    __tablename__ = "telemetry"
    __table_args__ = (Index(None, "run_id", "device", "t"),
                      CheckConstraint(_in("device", TELEMETRY_DEVICES), name="device"))

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    t: Mapped[float]
    device: Mapped[str] = mapped_column(String(16))
    chamber_pv: Mapped[float | None]
    chamber_sp: Mapped[float | None]
    chamber_ramp_sp: Mapped[float | None]
    chamber_mode: Mapped[int | None]
    chamber_alarm: Mapped[int | None]
    axis1_pos: Mapped[float | None]
    axis1_rate: Mapped[float | None]
    axis2_pos: Mapped[float | None]
    axis2_rate: Mapped[float | None]
    psu_volts: Mapped[float | None]
    psu_amps: Mapped[float | None]
    psu_on: Mapped[bool | None]


class Segment(Base):
    """A labelled stretch of bench time: which temperature point, orientation and repetition."""

    __tablename__ = "segments"
    __table_args__ = (Index(None, "run_id", "t_start"),
                      CheckConstraint(_in("kind", SEGMENT_KINDS), name="kind"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    step_index: Mapped[int | None]
    kind: Mapped[str] = mapped_column(String(16))
    temperature_c: Mapped[float | None]           # the temperature point (set point) of the segment
    orientation: Mapped[str | None] = mapped_column(String(32))
    outer_deg: Mapped[float | None]
    inner_deg: Mapped[float | None]
    repetition: Mapped[int] = mapped_column(default=0)
    t_start: Mapped[float]
    t_end: Mapped[float | None]                   # NULL while the segment is open
    labels: Mapped[dict[str, Any] | None]


GAP_KINDS = ("link", "corruption", "crash_resume", "suspension")
# when reports of one outage disagree, the later kind in this order wins (a crash/resume explains a
# suspension's silence, which explains a link's, which explains a sequence jump)
GAP_KINDS_BY_RANK = ("corruption", "link", "suspension", "crash_resume")


class Gap(Base):
    """One outage: time with missing frames and how many (``frames_missing``, from the sequence counter
    and the data rate).  ``reason`` is its kind (GAP_KINDS): ``link`` (the line was down or silent),
    ``corruption`` (frames rejected on the line, a sequence jump), ``crash_resume`` (the writer
    resumed the run after a crash), ``suspension`` (the run was suspended)."""

    __tablename__ = "gaps"
    __table_args__ = (Index(None, "run_id", "t_from"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    t_from: Mapped[float]
    t_to: Mapped[float]
    reason: Mapped[str] = mapped_column(String(64))
    frames_missing: Mapped[int | None] = mapped_column(BigInteger)
    after_index: Mapped[int | None] = mapped_column(BigInteger)   # last stored frame before the gap


class Suspension(Base):
    __tablename__ = "suspensions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    t_from: Mapped[float]
    t_to: Mapped[float | None]
    reason: Mapped[str] = mapped_column(Text)


class Fit(Base):
    """A fitted model for one channel.  ``version`` counts per (gyro, model); one fitting session
    storing x, y, z gets one version number."""

    __tablename__ = "fits"
    __table_args__ = (UniqueConstraint("gyro_id", "model", "channel", "version"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    gyro_id: Mapped[str] = mapped_column(ForeignKey("gyros.gyro_id"))
    run_ids: Mapped[list[Any]] = mapped_column(default=list)
    model: Mapped[str] = mapped_column(String(32))
    channel: Mapped[str] = mapped_column(String(16))
    version: Mapped[int]
    coefficients: Mapped[dict[str, Any]] = mapped_column(default=dict)
    result: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    accepted: Mapped[bool] = mapped_column(Boolean, default=False)


# ---------------------------------------------------------------- operator service (0002_service)
CONTROL_COMMANDS = ("stop", "abort", "pause", "resume")
ANALYSIS_STATUSES = ("queued", "running", "done", "failed")


class RunRequest(Base):
    """An operator request for a run, written by the API, consumed in order by the run's worker."""

    __tablename__ = "run_requests"
    __table_args__ = (Index(None, "run_id", "consumed_at"),
                      CheckConstraint(_in("command", CONTROL_COMMANDS), name="command"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    command: Mapped[str] = mapped_column(String(16))
    requested_by: Mapped[str] = mapped_column(String(64), default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    consumed_at: Mapped[dt.datetime | None]


JOB_KINDS = ("fit", "close_loop", "fit_report")


class Analysis(Base):
    """A durable analysis job (``kind`` one of JOB_KINDS) requested through the API, with its result.

    Workers claim jobs like runs (``bench.jobs``): ``worker`` holds the job while ``heartbeat_at`` is
    fresh; a job whose heartbeat went stale is claimed again and re-run (``attempts`` counts claims).
    Only the holder may finish it (the finishing ``UPDATE`` is guarded by ``worker``).  ``report_html``
    is the report page, rendered once by the job; ``fit_id`` is the fit version (its smallest row id)
    a fit or fit-report job produced or rendered (0004_analysis_jobs)."""

    __tablename__ = "analyses"
    __table_args__ = (CheckConstraint(_in("status", ANALYSIS_STATUSES), name="status"),
                      Index(None, "status", "id"), Index(None, "fit_id"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    gyro_id: Mapped[str | None] = mapped_column(String(64))
    request: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    result: Mapped[dict[str, Any] | None]
    error: Mapped[str | None] = mapped_column(Text)
    requested_by: Mapped[str] = mapped_column(String(64), default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[dt.datetime | None]
    worker: Mapped[str | None] = mapped_column(String(128))
    heartbeat_at: Mapped[dt.datetime | None]
    started_at: Mapped[dt.datetime | None]
    attempts: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    fit_id: Mapped[int | None] = mapped_column(Integer)
    report_html: Mapped[str | None] = mapped_column(Text)

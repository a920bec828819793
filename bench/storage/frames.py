"""Batched, crash-safe writer of a run's gyro frames (and its other time series).

``FrameWriter(db, run_id)`` takes ``GyroFrame`` objects as they come off the link and writes them in
timed batches from a background thread: every ``flush_interval_s`` wall seconds (default 0.5) or as
soon as ``flush_frames`` frames are waiting, never only at the end.

* Indexes: the writer gives every frame the next per-run index.  The index after the last stored
  frame is kept in ``frame_cursors`` and updated in the **same transaction** as the chunks, so a
  crash between batches loses only unwritten frames, never duplicates an index; a new writer
  continues from the stored cursor and records the interruption as a ``resume`` gap.
* Fencing: a new writer for the run takes the cursor over (``writer_token``); a stale writer that
  still tries to write gets ``WriterFenced`` instead of interleaving indexes.
* Outages: when the database cannot be reached (PostgreSQL restart, SQLite lock) everything stays
  in memory (bounded by ``max_buffered_frames`` / ``max_buffered_rows``; beyond that ``add`` raises
  ``BufferFull``) and the batch is retried with exponential backoff.  If the connection died while
  committing, the writer reads ``frame_cursors.batch_seq`` before retrying, so a batch whose commit
  went through is not written twice.  ``status()`` reports buffered counts and the last error.
* Gaps: one row per outage with its kind (``GAP_KINDS``) and ``frames_missing``.  A jump of the
  frame sequence counter (KVH: 0..127, device-protocols.md 3.1) counts the frames lost modulo the
  counter; whole turns hidden in it are counted with the data rate once the frames after it show the
  host clock staying ahead of the counted time (a late read does not; see ``_CountedClock``).  Link
  outages the engine learns from ``LinkStats.link_gaps`` and crash/resume go in with ``record_gap``;
  while the run is suspended (``begin_suspension`` / ``end_suspension``) frames that stop are lost to
  the ``suspension``.
* Per-second sums (``frame_seconds``) of valid-status frames are computed with numpy when a chunk
  is sealed and upserted with the chunks, so 1-s means never need the raw frames.

Probe readings, device telemetry, events and finished segments can go through the same writer so
they share the buffering and batching (``add_probe_readings``, ``add_chamber``, ``add_turntable``,
``add_psu``, ``add_event``, ``add_segment``).
"""
from __future__ import annotations

import logging
import math
import threading
import time
import uuid
import weakref
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import bindparam, insert, select, update
from sqlalchemy.exc import DBAPIError, InterfaceError, OperationalError

from bench.interfaces import AxisState, ChamberStatus, GyroFrame, ProbeReading
from bench.storage import codec
from bench.storage.db import Database
from bench.storage.errors import BufferFull, StorageError, StorageUnavailable, UnknownRun, WriterFenced
from bench.storage.models import (SECONDS_PER_BLOCK, SEGMENT_KINDS, SUM_FIELDS, Event, FrameChunk, FrameCursor,
                                  FrameSecond, GAP_KINDS, GAP_KINDS_BY_RANK, Gap, ProbeReadingRow, Run, Segment,
                                  Telemetry, utcnow)

log = logging.getLogger(__name__)

_SUM_COLUMNS = SUM_FIELDS
_ROW_TABLES = {"gaps": Gap.__table__, "probe_readings": ProbeReadingRow.__table__,
               "telemetry": Telemetry.__table__, "events": Event.__table__, "segments": Segment.__table__}
# a telemetry row: every column but the key, in table order; the values a caller may give
_TELEMETRY_ROW = tuple(c for c in Telemetry.__table__.c.keys() if c != "id")
_TELEMETRY_VALUES = frozenset(_TELEMETRY_ROW) - {"run_id", "t", "device"}


@dataclass(frozen=True)
class WriterStatus:
    run_id: int
    next_index: int                 # index the next added frame will get
    committed_frames: int           # frames this writer has committed
    committed_index: int            # next index according to the last commit (frames below are durable)
    buffered_frames: int            # accepted but not yet committed
    buffered_rows: int              # other rows (gaps, probes, telemetry, events...) not yet committed
    retries: int                    # failed write attempts so far
    last_error: str | None
    last_error_wall: float | None   # time.time() of the last failure
    last_commit_wall: float | None
    fatal: str | None               # set when the writer stopped for good (fenced, constraint error)
    closed: bool

    @property
    def healthy(self) -> bool:
        return self.fatal is None and (self.last_error_wall is None or
                                       (self.last_commit_wall or 0) > self.last_error_wall)


@dataclass
class _Summary:
    """Per-second sums of one or more chunks (arrays aligned on ``second``)."""

    second: np.ndarray
    cols: dict[str, np.ndarray]
    has_freq: bool

    @staticmethod
    def merge(parts: Sequence["_Summary"]) -> "_Summary":
        seconds = np.concatenate([p.second for p in parts])
        uniq, inv = np.unique(seconds, return_inverse=True)
        has_freq = any(p.has_freq for p in parts)
        cols = {}
        for name in _SUM_COLUMNS:
            if name.startswith("sum_f") and not has_freq:
                continue
            values = np.concatenate([p.cols.get(name, np.zeros(p.second.size)) for p in parts])
            cols[name] = np.bincount(inv, weights=values, minlength=uniq.size)
        return _Summary(uniq, cols, has_freq)

    def blocks(self) -> dict[int, np.ndarray]:
        """{first second of block: (SECONDS_PER_BLOCK, len(SUM_FIELDS)) float64 sums}."""
        table = np.column_stack([self.cols.get(name, np.zeros(self.second.size)) for name in SUM_FIELDS])
        starts = self.second - self.second % SECONDS_PER_BLOCK
        out: dict[int, np.ndarray] = {}
        for start in np.unique(starts).tolist():
            sel = starts == start
            arr = np.zeros((SECONDS_PER_BLOCK, len(SUM_FIELDS)))
            arr[self.second[sel] - start] = table[sel]
            out[start] = arr
        return out


@dataclass
class _Chunk:
    first_index: int
    count: int
    t_first: float
    t_last: float
    kind: str
    size: int
    raw: bytes
    dt_us: bytes
    temp_centi: bytes
    summary: _Summary

    def row(self, run_id: int) -> dict[str, Any]:
        return {"run_id": run_id, "first_index": self.first_index, "count": self.count, "t_first": self.t_first,
                "t_last": self.t_last, "frame_kind": self.kind, "frame_size": self.size, "raw": self.raw,
                "dt_us": self.dt_us, "temp_centi": self.temp_centi}


@dataclass
class _Batch:
    chunks: list[_Chunk]
    rows: dict[str, list[dict[str, Any]]]
    seq: int
    frames: int = field(init=False)

    def __post_init__(self) -> None:
        self.frames = sum(c.count for c in self.chunks)

    @property
    def empty(self) -> bool:
        return not self.chunks and not any(self.rows.values())


@dataclass
class _Outage:
    """A reported outage whose frame count the next frame settles."""
    kind: str
    t_from: float


class _CountedClock:
    """The frames' bench time by the sequence counter and the data rate (``anchor + n / rate``, ``n`` the
    frames counted, lost ones included), held against the host stamps.

    ``offset`` = host stamp - counted time is how late the host read the frame (plus a constant).  Some
    reads come late, but not all: the ``floor`` of the offsets is the prompt reads' latency.  A loss of
    whole turns that the counter cannot show lifts the floor for good (``modulus / rate`` per turn); a
    late read lifts single offsets only.  The floor may rise by ``DRIFT`` per counted second (the device
    and host clocks drift apart)."""

    DRIFT = 1e-3

    def __init__(self, host: float, rate: float) -> None:
        self.anchor, self.rate, self.n = host, rate, 0
        self.floor, self.floor_n = 0.0, 0

    def advance(self, steps: int, host: float) -> float:
        """Count ``steps`` frames (one plus those lost before it); the new frame's offset."""
        self.n += steps
        return host - (self.anchor + self.n / self.rate)

    def note(self, offset: float) -> None:
        self.floor = min(offset, self.floor + self.DRIFT * (self.n - self.floor_n) / self.rate)
        self.floor_n = self.n


@dataclass
class _TurnCheck:
    """Jumps of the counter that the host clock leaves room for whole turns in, waiting for the frames
    after them.  ``rows``: per jump, [its gap row (the counter's count), the turns the host clock has room
    for, the lowest offset since the jump]; ``until_n`` the count that settles them all."""
    floor_before: float
    rows: list[list[Any]] = field(default_factory=list)
    until_n: int = 0

    def join(self, row: dict[str, Any], room: int, offset: float, until_n: int) -> None:
        self.rows.append([row, room, offset])
        self.until_n = until_n

    def see(self, offset: float) -> None:
        for entry in self.rows:
            if offset < entry[2]:
                entry[2] = offset

    def turns(self, turn_s: float) -> list[int]:
        """Whole turns lost at each jump: how far the lowest offset after it stands above the level the
        jumps before it explain, within the host clock's room."""
        level, out = self.floor_before, []
        for _, room, after in self.rows:
            n = max(0, min(room, round((after - level) / turn_s)))
            level += n * turn_s
            out.append(n)
        return out


def gap_kind(reason: str) -> str:
    """The kind of an outage (``GAP_KINDS``) from the words of whoever reported it."""
    text = reason.lower()
    if text in GAP_KINDS:
        return text
    if "link" in text:
        return "link"
    if "interrupt" in text or "resume" in text or "crash" in text:
        return "crash_resume"
    if "suspen" in text:
        return "suspension"
    if "corrupt" in text or "sequence" in text:
        return "corruption"
    return reason[:64]          # a reporter's own word, kept


def gap_rank(kind: str) -> int:
    """Which kind an outage keeps when several reports name it (``GAP_KINDS_BY_RANK``: corruption, link,
    suspension, crash/resume); a reporter's own word ranks as a link."""
    return GAP_KINDS_BY_RANK.index(kind) if kind in GAP_KINDS_BY_RANK else 1


def _last_sequence(kind: str, size: int, raw: bytes) -> int | None:
    """The sequence number of the last frame of a stored chunk (None when the layout has none)."""
    try:
        decoded = codec.decode_frames(kind, raw[-size:], size)
    except (codec.UnknownFrameKind, ValueError):
        return None
    seq = getattr(decoded, "sequence", None)
    return int(seq[-1]) if seq is not None and len(seq) else None


def _is_transient(exc: BaseException) -> bool:
    if isinstance(exc, (OperationalError, InterfaceError)):
        return True
    return isinstance(exc, DBAPIError) and bool(exc.connection_invalidated)


def _short(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None)
    text = str(orig if orig is not None else exc).strip()
    return f"{type(orig or exc).__name__}: {text.splitlines()[0] if text else ''}"


_LIVE: "weakref.WeakSet[FrameWriter]" = weakref.WeakSet()     # every writer of this process (metrics)


_INSERTS: dict[tuple, tuple[str, tuple[str, ...], tuple]] = {}


def _insert_rows(conn, table, rows: list[dict[str, Any]]) -> None:
    """``INSERT`` of ``rows`` (dicts of column values, all with the same keys) into ``table``, as
    ``conn.execute(insert(table), rows)`` stores them.  With a positional DBAPI (SQLite's ``?``) the statement
    is compiled once per table, keys and dialect, each value goes through its column's bind processor, and
    the rows go to the driver's ``executemany`` as tuples: SQLAlchemy's per-row parameter handling costs
    more than SQLite's own insert (a campaign's writers store every probe reading of every unit).  Rows
    with other keys than the first, and named-parameter drivers, take ``conn.execute``."""
    keys = tuple(rows[0])
    dialect = conn.dialect
    key = (table.name, keys, dialect.name, dialect.paramstyle)
    plan = _INSERTS.get(key)
    if plan is None:
        compiled = insert(table).compile(dialect=dialect, column_keys=list(keys))
        if compiled.positional and set(compiled.positiontup) == set(keys):
            names = tuple(compiled.positiontup)
            procs = compiled._bind_processors
            plan = (str(compiled), names, tuple(procs.get(n) for n in names))
        else:
            plan = ("", (), ())
        _INSERTS[key] = plan
    sql, names, procs = plan
    if not sql or any(len(r) != len(keys) or r.keys() != rows[0].keys() for r in rows):
        conn.execute(insert(table), rows)
        return
    params = [tuple(v if f is None else f(v) for f, v in zip(procs, [r[n] for n in names])) for r in rows]
    conn.exec_driver_sql(sql, params)


def live_writer_statuses() -> list["WriterStatus"]:
    """``status()`` of every frame writer of this process that is not closed (for ``bench.metrics``)."""
    return [st for st in (w.status() for w in list(_LIVE)) if not st.closed]


class FrameWriter:
    """Background batched writer for one run.  Thread-safe; see the module docstring.

    Parameters: ``frame_kind`` names the raw layout (``"kvh_a"``, ``"hrg"``...; decoding on read needs
    a registered layout, writing does not); ``valid_status`` is the status byte of a frame whose
    values all count (KVH: 0x77; ``None`` = every frame counts); ``sequence_modulus`` the wrap of the
    sequence counter (KVH: 128; ``None`` = no sequence check); ``nominal_rate_hz`` refines missing
    frame estimates.  ``autostart=False`` keeps the background thread off (``flush()`` then writes
    synchronously) - useful for deterministic tests and benchmarks.
    """

    def __init__(self, db: Database, run_id: int, *, frame_kind: str = "kvh_a", chunk_frames: int = 1000,
                 flush_interval_s: float = 0.5, flush_frames: int = 20_000,
                 max_buffered_frames: int = 5_000_000, max_buffered_rows: int = 1_000_000,
                 valid_status: int | None = 0x77, sequence_modulus: int | None = 128,
                 nominal_rate_hz: float | None = None, resume_reason: str = "resume",
                 retry_initial_s: float = 0.1, retry_max_s: float = 5.0, autostart: bool = True) -> None:
        if chunk_frames < 1 or flush_frames < 1 or max_buffered_frames < chunk_frames:
            raise ValueError("chunk_frames and flush_frames must be >= 1 and max_buffered_frames >= chunk_frames")
        self.db = db
        self.run_id = int(run_id)
        self.frame_kind = frame_kind
        self.chunk_frames = chunk_frames
        self.flush_interval_s = flush_interval_s
        self.flush_frames = flush_frames
        self.max_buffered_frames = max_buffered_frames
        self.max_buffered_rows = max_buffered_rows
        self.valid_status = valid_status
        self.sequence_modulus = sequence_modulus
        self.nominal_rate_hz = nominal_rate_hz
        self.retry_initial_s = retry_initial_s
        self.retry_max_s = retry_max_s
        self._resume_reason = resume_reason
        self._expected_size = codec.known_frame_size(frame_kind)
        self._token = uuid.uuid4().hex
        self._cond = threading.Condition()
        self._open: list[GyroFrame] = []
        self._open_times: list[float] = []         # the stored times of the open frames
        self._chunks: list[_Chunk] = []
        self._rows: dict[str, list[dict[str, Any]]] = {name: [] for name in _ROW_TABLES}
        self._n_rows = 0
        self._rows_queued = 0          # totals, so flush() can wait for rows queued before it
        self._rows_committed = 0
        self._inflight: _Batch | None = None   # batch whose write failed: retried as is
        self._block_cache: dict[int, tuple[bool, np.ndarray]] = {}    # frame_seconds rows as last committed
        self._pending_cache: dict[int, tuple[bool, np.ndarray]] | None = None
        self._buffered_frames = 0
        self._committed_frames = 0
        self._seq = 0
        self._retries = 0
        self._last_error: str | None = None
        self._last_error_wall: float | None = None
        self._last_commit_wall: float | None = None
        self._last_flush_mono = time.monotonic()
        self._flush_requested = False
        self._fatal: BaseException | None = None
        self._closing = False
        self._abandoned = False
        self._closed = False
        self._thread: threading.Thread | None = None
        self._prev_seq: int | None = None
        self._prev_time: float | None = None       # stored time of the last frame
        self._prev_host: float | None = None       # its host time
        self._counted: _CountedClock | None = None    # the frames' time by the counter, against the host's
        self._turn_check: _TurnCheck | None = None     # jumps whose hidden turns the next frames settle
        self._suspensions: list[list[float | None]] = []   # recent [t_from, t_to or None] of the run's suspensions
        self._by_seq: dict[int, int] = {}          # recent gap rows (by id): frames lost by the counter alone
        self._take_over()
        _LIVE.add(self)
        if autostart:
            self._thread = threading.Thread(target=self._run, name=f"frame-writer-run{self.run_id}", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ setup
    def _take_over(self) -> None:
        """Fence off any previous writer, then read (or create) the run's cursor.

        The token is written first: that write waits for a previous writer's batch in flight (its row
        lock on PostgreSQL, the write lock on SQLite) and makes its next batch fail (``WriterFenced``), so
        the cursor and chunks read after it are final.  Read first, a batch the previous writer
        committed in between would end where this writer starts (a duplicate first index)."""
        try:
            with self.db.engine.begin() as conn:
                if conn.execute(select(Run.id).where(Run.id == self.run_id)).first() is None:
                    raise UnknownRun(f"run {self.run_id} does not exist in {self.db.url}")
                conn.execute(update(FrameCursor).where(FrameCursor.run_id == self.run_id)
                             .values(writer_token=self._token, updated_at=utcnow()))
                cur = conn.execute(select(FrameCursor.next_index, FrameCursor.batch_seq, FrameCursor.t_last)
                                   .where(FrameCursor.run_id == self.run_id)).first()
                last = conn.execute(select(FrameChunk.first_index, FrameChunk.count, FrameChunk.t_first,
                                           FrameChunk.t_last, FrameChunk.frame_kind, FrameChunk.frame_size,
                                           FrameChunk.raw).where(FrameChunk.run_id == self.run_id)
                                    .order_by(FrameChunk.first_index.desc()).limit(1)).first()
                stored_next = last.first_index + last.count if last else 0
                if cur is None:
                    conn.execute(insert(FrameCursor).values(run_id=self.run_id, next_index=stored_next, batch_seq=0,
                                                            writer_token=self._token,
                                                            t_last=last.t_last if last else None))
                    next_index, seq = stored_next, 0
                else:
                    if cur.next_index != stored_next:
                        raise StorageError(f"run {self.run_id}: frame cursor says next index {cur.next_index} "
                                           f"but stored chunks end at {stored_next}")
                    next_index, seq = cur.next_index, cur.batch_seq
        except OperationalError as exc:
            raise StorageUnavailable(f"run {self.run_id}: cannot open frame writer: {_short(exc)}") from None
        self._next_index = next_index
        self._committed_index = next_index
        self._seq = seq
        self._outage: _Outage | None = None
        self._measured_rate: float | None = None
        if last is not None:
            # the run resumes after a crash: the next frame closes a crash/resume outage, counted from the
            # last stored frame's sequence number (decoded from its stored bytes) and the elapsed time
            rate = (last.count - 1) / (last.t_last - last.t_first) if last.t_last > last.t_first else None
            self._measured_rate = rate
            self._prev_time = float(last.t_last)
            self._prev_seq = _last_sequence(last.frame_kind, last.frame_size, last.raw)
            self._outage = _Outage(gap_kind(self._resume_reason), float(last.t_last))

    # ------------------------------------------------------------------ producer API
    def add(self, frame: GyroFrame) -> int:
        """Accept one frame; returns the index it gets."""
        return self.add_many((frame,))

    def add_many(self, frames: Iterable[GyroFrame]) -> int:
        """Accept frames in order; returns the index of the last one (or next_index - 1)."""
        with self._cond:
            self._check_usable()
            for frame in frames:
                self._add_locked(frame)
            if self._buffered_frames - len(self._open) >= self.flush_frames:
                self._cond.notify_all()
            return self._next_index - 1

    def _add_locked(self, frame: GyroFrame) -> None:
        size = len(frame.raw)
        if self._expected_size is not None and size != self._expected_size:
            raise codec.UnknownFrameKind(f"run {self.run_id}: a {self.frame_kind} frame must be "
                                         f"{self._expected_size} bytes, got {size} (frame seq {frame.sequence})")
        if self._buffered_frames >= self.max_buffered_frames:
            raise BufferFull(f"run {self.run_id}: {self._buffered_frames} frames buffered and the database is "
                             f"not taking them ({self._last_error or 'no error yet'})")
        t = self._stamp_and_account(frame)
        if self._open:
            if len(self._open[0].raw) != size or t - self._open_times[0] > codec.MAX_CHUNK_SPAN_S:
                self._seal_locked()
        self._prev_seq, self._prev_time = frame.sequence, t
        self._open.append(frame)
        self._open_times.append(t)
        self._next_index += 1
        self._buffered_frames += 1
        if len(self._open) >= self.chunk_frames:
            self._seal_locked()

    # ------------------------------------------------------------------ time and loss accounting
    @property
    def _rate(self) -> float | None:
        return self.nominal_rate_hz or self._measured_rate

    def _stamp_and_account(self, frame: GyroFrame) -> float:
        """The stored time of ``frame`` (strictly after the previous one), and a gap row when frames were
        lost before it.

        Frames lost: the sequence counter's advance minus one; without a counter, the elapsed time times
        the rate.  Whole turns of the counter (a loss it cannot show) are counted with the data rate:
        right away for an outage someone reported (a crash/resume, a link drop: its span is known), else
        by the counted clock (``_CountedClock``) once the frames after the jump prove them - the host
        stamps alone do not, since a host that reads late stamps old frames as new.  Stored time: the
        previous stored time plus the frames' advance over the rate, pulled gently (gain ``TIME_GAIN``)
        towards the host time: frames taken off the line in one read share a host time, but left the
        device one period apart.  After an outage (host time ahead by more than ``REANCHOR_S``) the host
        time is taken as it is."""
        host = frame.host_time
        prev_t, rate, mod = self._prev_time, self._rate, self.sequence_modulus
        prev_host, self._prev_host = self._prev_host, host
        if prev_t is None:
            self._restart_count(host)
            return host
        # elapsed on the host clock between the frames' stamps (a read's frames share one stamp; the
        # stored times follow the counter, so they would see the read latency as lost frames)
        elapsed = host - (prev_host if prev_host is not None else prev_t)
        by_time = elapsed * rate - 1 if rate else None
        known = self._outage is not None
        by_seq = (frame.sequence - self._prev_seq - 1) % mod if mod and self._prev_seq is not None else None
        room = max(0, round((by_time - by_seq) / mod)) if by_seq is not None and by_time is not None else 0
        if by_seq is None:
            missing = max(0, round(by_time)) if by_time is not None else None
        else:
            missing = by_seq + mod * room if known else by_seq
        if rate:
            predicted = prev_t + ((missing or 0) + 1) / rate
            error = host - predicted
            t = host if error > self.REANCHOR_S else predicted + self.TIME_GAIN * error
            t = max(t, prev_t + 0.5 / rate)
        else:
            t = max(host, prev_t + self.MIN_STEP_S)
        if known:
            kind, t_from = self._outage.kind, min(self._outage.t_from, prev_t)
            self._outage = None
            self._settle_turns()
            self._restart_count(host)
            self._queue_gap(self._gap_row(t_from, t, kind, missing), by_seq)
            return t
        counted = self._counted
        offset = counted.advance((missing or 0) + 1, host) if counted is not None else None
        if room and counted is not None:            # turns may hide in this jump: the next frames settle them
            row = self._gap_row(prev_t, t, "corruption", by_seq)
            if self._turn_check is None:
                self._turn_check = _TurnCheck(counted.floor)
            self._turn_check.see(offset)
            self._turn_check.join(row, room, offset, counted.n + round(self.TURN_SETTLE_S * rate))
            return t
        if missing:
            self._queue_gap(self._gap_row(prev_t, t, "corruption", missing), by_seq)
        check = self._turn_check
        if check is None:
            if counted is not None:
                counted.note(offset)
        else:
            check.see(offset)
            if counted.n >= check.until_n or len(check.rows) >= self.MAX_UNSETTLED:
                self._settle_turns()
        return t

    TIME_GAIN = 0.02            # per frame: the stored clock follows the host clock over ~50 frames
    REANCHOR_S = 1.0            # host time this far ahead of the counted time: an outage, restart from it
    TURN_SETTLE_S = 5.0         # bench s of frames after a jump that show whether whole turns were lost
    MAX_UNSETTLED = 64          # jumps waiting for that at most (each frame updates each of them)
    MIN_STEP_S = 2e-6           # without a rate: stored times still strictly increase (1 us resolution)

    def _restart_count(self, host: float) -> None:
        rate, mod = self._rate, self.sequence_modulus
        self._counted = _CountedClock(host, rate) if rate and mod else None

    def _gap_row(self, t_from: float, t_to: float, kind: str, missing: int | None) -> dict[str, Any]:
        return {"run_id": self.run_id, "t_from": t_from, "t_to": t_to, "reason": kind, "frames_missing": missing,
                "after_index": self._next_index - 1}

    def _queue_gap(self, row: dict[str, Any], by_seq: int | None) -> None:
        """Queue a gap row; a second's worth of frames or more lost without a reported outage: the line
        was down or silent (``link``), not noisy."""
        rate, missing = self._rate, row["frames_missing"]
        if row["reason"] == "corruption" and missing is not None and rate and missing >= rate * self.REANCHOR_S:
            row["reason"] = "link"
        row["reason"] = self._suspension_kind(row["reason"], row["t_from"], row["t_to"])
        self._queue_row("gaps", row)
        if by_seq is not None:
            self._by_seq[id(row)] = by_seq
            while len(self._by_seq) > 256:
                self._by_seq.pop(next(iter(self._by_seq)))

    def _settle_turns(self) -> None:
        """Close the open turn check: add the whole turns it shows to its jumps' rows, count them in the
        counted clock, queue the rows."""
        check, counted = self._turn_check, self._counted
        if check is None:
            return
        self._turn_check = None
        assert counted is not None and self.sequence_modulus and self._rate
        mod, turn_s = self.sequence_modulus, self.sequence_modulus / self._rate
        turns = check.turns(turn_s)
        counted.n += mod * sum(turns)
        counted.floor = min(counted.floor, check.rows[-1][2] - sum(turns) * turn_s)
        for (row, _, _), n in zip(check.rows, turns):
            by_seq = row["frames_missing"]
            row["frames_missing"] = by_seq + mod * n
            if row["frames_missing"]:
                self._queue_gap(row, by_seq)

    def record_gap(self, t_from: float, t_to: float, reason: str, frames_missing: int | None = None) -> None:
        """Record a known outage (a link gap from ``LinkStats.link_gaps``, the engine's interruption on
        resume), one gap row per outage: if the frames after it already arrived, the row their sequence
        jump made is that outage's row (its kind becomes this one's); if not, the next frame closes it and
        counts its frames.  ``frames_missing`` given: stored as is in a row of its own."""
        if not t_to >= t_from:
            raise ValueError(f"gap t_to {t_to} is before t_from {t_from}")
        with self._cond:
            self._check_usable()
            kind = self._suspension_kind(gap_kind(reason), t_from, t_to)
            if frames_missing is None:
                if self._relabel_gap(t_from, t_to, kind):
                    return
                if self._prev_time is None or t_to >= self._prev_time:
                    start = t_from if self._outage is None else min(t_from, self._outage.t_from)
                    self._outage = _Outage(kind if self._outage is None else max(kind, self._outage.kind,
                                                                                          key=gap_rank), start)
                    return
                log.warning("run %s: %s outage %.3f-%.3f reported after its frames were stored; its frames "
                            "are counted in the row of the sequence jump", self.run_id, kind, t_from, t_to)
                return
            self._queue_row("gaps", {"run_id": self.run_id, "t_from": float(t_from), "t_to": float(t_to),
                                     "reason": kind, "frames_missing": frames_missing,
                                     "after_index": self._next_index - 1 if self._next_index else None})

    def begin_suspension(self, t_from: float) -> None:
        """The run is suspended from bench time ``t_from`` (``end_suspension`` closes it): frames that stop
        meanwhile were lost to the suspension, and their gap row says so (kind ``suspension``, not
        ``link``); a noisy line while suspended is still ``corruption``."""
        with self._cond:
            self._suspensions.append([float(t_from), None])
            del self._suspensions[:-16]

    def end_suspension(self, t_to: float) -> None:
        with self._cond:
            if self._suspensions and self._suspensions[-1][1] is None:
                self._suspensions[-1][1] = float(t_to)

    def _suspension_kind(self, kind: str, t_from: float, t_to: float) -> str:
        """``suspension`` for an outage of a link's rank or less that overlaps a suspension, else ``kind``."""
        if gap_rank(kind) > gap_rank("link") or kind == "corruption":
            return kind
        for a, b in self._suspensions:
            if a <= t_to and (b is None or b >= t_from):
                return "suspension"
        return kind

    def _relabel_gap(self, t_from: float, t_to: float, kind: str) -> bool:
        """The queued (or still unsettled) gap row that a reported outage ``t_from``-``t_to`` overlaps is
        that outage's row: it takes the higher ranked kind of the two (``gap_rank``), and the outage's own
        span settles its counter's turns; False: none overlaps."""
        check = self._turn_check
        pending = [entry[0] for entry in check.rows] if check is not None else []
        for row in [*reversed(pending), *reversed(self._rows["gaps"])]:
            if not (row["t_from"] <= t_to and row["t_to"] >= t_from):
                continue
            unsettled = any(r is row for r in pending)
            by_seq = row["frames_missing"] if unsettled else self._by_seq.get(id(row))
            mod, rate = self.sequence_modulus, self._rate
            if by_seq is not None and mod and rate:
                span = (max(t_to, row["t_to"]) - min(t_from, row["t_from"])) * rate - 1
                row["frames_missing"] = by_seq + mod * max(0, round((span - by_seq) / mod))
            row["reason"] = max(row["reason"], kind, key=gap_rank)
            if unsettled:                            # known now: it waits for no more evidence
                check.rows = [entry for entry in check.rows if entry[0] is not row]
                if not check.rows:
                    self._turn_check = None
                self._queue_gap(row, by_seq)
            return True
        return False

    def add_probe_readings(self, t: float, readings: Iterable[ProbeReading]) -> None:
        with self._cond:
            self._check_usable()
            for r in readings:
                self._queue_row("probe_readings", {"run_id": self.run_id, "t": float(t), "name": r.name,
                                                   "serial": r.serial, "celsius": r.celsius, "fault": r.fault})

    def add_chamber(self, t: float, status: ChamberStatus) -> None:
        self.add_telemetry(t, "chamber", chamber_pv=status.pv_c, chamber_sp=status.setpoint_c,
                           chamber_ramp_sp=status.ramp_setpoint_c, chamber_mode=status.mode,
                           chamber_alarm=status.alarm)

    def add_turntable(self, t: float, axes: Mapping[int, AxisState]) -> None:
        cols: dict[str, Any] = {}
        for axis, state in axes.items():
            if axis not in (1, 2):
                raise ValueError(f"turntable axis {axis}: telemetry stores axes 1 and 2 only")
            cols[f"axis{axis}_pos"] = state.position_deg
            cols[f"axis{axis}_rate"] = state.rate_dps
        self.add_telemetry(t, "turntable", **cols)

    def add_psu(self, t: float, volts: float | None, amps: float | None, on: bool | None) -> None:
        self.add_telemetry(t, "psu", psu_volts=volts, psu_amps=amps, psu_on=on)

    def add_telemetry(self, t: float, device: str, **values: Any) -> None:
        unknown = [k for k in values if k not in _TELEMETRY_VALUES]
        if unknown:
            raise ValueError(f"telemetry has no column(s) {unknown}")
        row = dict.fromkeys(_TELEMETRY_ROW)
        row.update(values, run_id=self.run_id, t=float(t), device=device)
        with self._cond:
            self._check_usable()
            self._queue_row("telemetry", row)

    def add_event(self, kind: str, message: str, *, t_bench: float | None = None,
                  data: dict[str, Any] | None = None) -> None:
        with self._cond:
            self._check_usable()
            self._queue_row("events", {"run_id": self.run_id, "t_bench": t_bench, "wall_time": utcnow(),
                                       "kind": kind, "message": message, "data": data})

    def add_segment(self, kind: str, t_start: float, t_end: float, *, temperature_c: float | None = None,
                    orientation: str | None = None, outer_deg: float | None = None,
                    inner_deg: float | None = None, repetition: int = 0, step_index: int | None = None,
                    labels: dict[str, Any] | None = None) -> None:
        """A finished labelled segment (``bench.storage.queries.open_segment`` writes open ones directly)."""
        if kind not in SEGMENT_KINDS:
            raise ValueError(f"segment kind {kind!r} is not one of {SEGMENT_KINDS}")
        with self._cond:
            self._check_usable()
            self._queue_row("segments", {"run_id": self.run_id, "step_index": step_index, "kind": kind,
                                         "temperature_c": temperature_c, "orientation": orientation,
                                         "outer_deg": outer_deg, "inner_deg": inner_deg, "repetition": repetition,
                                         "t_start": float(t_start), "t_end": float(t_end), "labels": labels})

    def _queue_row(self, table: str, row: dict[str, Any]) -> None:
        if self._n_rows >= self.max_buffered_rows:
            raise BufferFull(f"run {self.run_id}: {self._n_rows} rows buffered and the database is not taking "
                             f"them ({self._last_error or 'no error yet'})")
        self._rows[table].append(row)
        self._n_rows += 1
        self._rows_queued += 1

    def _check_usable(self) -> None:
        if self._fatal is not None:
            raise self._fatal if isinstance(self._fatal, StorageError) else StorageError(
                f"run {self.run_id}: frame writer stopped: {_short(self._fatal)}")
        if self._closing or self._closed:
            raise StorageError(f"run {self.run_id}: frame writer is closed")

    # ------------------------------------------------------------------ sealing
    def _seal_locked(self) -> None:
        frames = self._open
        if not frames:
            return
        times = np.asarray(self._open_times, dtype=np.float64)
        self._open, self._open_times = [], []
        n = len(frames)
        gyro = np.array([f.gyro for f in frames], dtype=np.float64).reshape(n, 3)
        accel = np.array([f.accel for f in frames], dtype=np.float64).reshape(n, 3)
        temps = np.fromiter((math.nan if f.temperature_c is None else f.temperature_c for f in frames),
                            np.float64, n)
        has_freq = any(f.freq_hz is not None for f in frames)
        freq = (np.array([f.freq_hz if f.freq_hz is not None else (math.nan,) * 3 for f in frames],
                         dtype=np.float64).reshape(n, 3) if has_freq else None)
        t_first, dt_us = codec.pack_times(times)
        times = codec.unpack_times(t_first, dt_us)   # summarise the stored (1 us) times: re-derivable
        chunk = _Chunk(first_index=self._next_index - n, count=n, t_first=t_first, t_last=float(times[-1]),
                       kind=self.frame_kind, size=len(frames[0].raw), raw=b"".join([f.raw for f in frames]),
                       dt_us=dt_us, temp_centi=codec.pack_temps(temps),
                       summary=self._summarise(frames, times, gyro, accel, temps, freq))
        self._chunks.append(chunk)

    def _summarise(self, frames: list[GyroFrame], times: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                   temps: np.ndarray, freq: np.ndarray | None) -> _Summary:
        valid = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        if freq is not None:
            valid &= np.isfinite(freq).all(axis=1)
        if self.valid_status is not None:
            status = np.fromiter((f.status for f in frames), np.int64, len(frames))
            valid &= status == self.valid_status
        seconds = np.floor(times).astype(np.int64)
        uniq, inv = np.unique(seconds, return_inverse=True)

        def total(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
            return np.bincount(inv, weights=np.where(mask, values, 0.0), minlength=uniq.size)

        cols = {"n": np.bincount(inv, weights=valid.astype(np.float64), minlength=uniq.size),
                "n_invalid": np.bincount(inv, weights=(~valid).astype(np.float64), minlength=uniq.size),
                "sum_dt": total(times - seconds, valid)}
        for i, axis in enumerate("xyz"):
            cols[f"sum_g{axis}"] = total(gyro[:, i], valid)
            cols[f"sum_a{axis}"] = total(accel[:, i], valid)
        temp_ok = np.isfinite(temps)
        cols["n_temp"] = np.bincount(inv, weights=temp_ok.astype(np.float64), minlength=uniq.size)
        cols["sum_temp"] = total(temps, temp_ok)
        if freq is not None:
            for i, axis in enumerate("xyz"):
                cols[f"sum_f{axis}"] = total(freq[:, i], valid)
        return _Summary(uniq, cols, freq is not None)

    # ------------------------------------------------------------------ writing
    MAX_BATCH_CHUNKS = 500
    MAX_BATCH_ROWS = 50_000

    def _take_batch_locked(self, seal_open: bool) -> _Batch:
        """The batch to write next: the failed one again if any (its commit may have gone through),
        else a prefix of what is buffered."""
        if self._inflight is not None:
            return self._inflight
        if seal_open:
            self._seal_locked()
        return _Batch(chunks=self._chunks[:self.MAX_BATCH_CHUNKS],
                      rows={k: v[:self.MAX_BATCH_ROWS] for k, v in self._rows.items()}, seq=self._seq + 1)

    def _write(self, batch: _Batch) -> None:
        with self.db.engine.begin() as conn:
            values: dict[str, Any] = {"batch_seq": batch.seq, "updated_at": utcnow()}
            if batch.chunks:
                last = batch.chunks[-1]
                values.update(next_index=last.first_index + last.count, t_last=last.t_last)
            res = conn.execute(update(FrameCursor).where(FrameCursor.run_id == self.run_id,
                                                         FrameCursor.writer_token == self._token).values(**values))
            if res.rowcount != 1:
                raise WriterFenced(f"run {self.run_id}: another frame writer has taken this run over; "
                                   f"{batch.frames} frames of this writer were not stored")
            if batch.chunks:
                conn.execute(insert(FrameChunk), [c.row(self.run_id) for c in batch.chunks])
                self._write_seconds(conn, _Summary.merge([c.summary for c in batch.chunks]))
            for name, rows in batch.rows.items():
                if rows:
                    _insert_rows(conn, _ROW_TABLES[name], rows)

    def _write_seconds(self, conn, summary: _Summary) -> None:
        """Add the batch's per-second sums to the frame_seconds blocks (read-modify-write: this writer
        is the run's only writer, see fencing; blocks it committed last are cached)."""
        delta = summary.blocks()
        missing = [b for b in delta if b not in self._block_cache]
        stored: dict[int, tuple[bool, np.ndarray]] = {}
        for i in range(0, len(missing), 500):
            rows = conn.execute(select(FrameSecond.block, FrameSecond.has_freq, FrameSecond.sums)
                                .where(FrameSecond.run_id == self.run_id,
                                       FrameSecond.block.in_(missing[i:i + 500]))).all()
            stored.update({b: (hf, np.frombuffer(raw, dtype="<f8").reshape(SECONDS_PER_BLOCK, -1))
                           for b, hf, raw in rows})
        inserts, updates, new_cache = [], [], {}
        for block, arr in delta.items():
            base = self._block_cache.get(block) or stored.get(block)
            has_freq = summary.has_freq or (base is not None and base[0])
            total = arr if base is None else base[1] + arr
            params = {"p_run": self.run_id, "p_block": block, "p_hf": has_freq,
                      "p_sums": total.astype("<f8").tobytes()}
            (inserts if base is None else updates).append(params)
            new_cache[block] = (has_freq, total)
        t = FrameSecond.__table__
        if inserts:
            conn.execute(insert(t).values(run_id=bindparam("p_run"), block=bindparam("p_block"),
                                          has_freq=bindparam("p_hf"), sums=bindparam("p_sums")), inserts)
        if updates:
            conn.execute(update(t).where(t.c.run_id == bindparam("p_run"), t.c.block == bindparam("p_block"))
                         .values(has_freq=bindparam("p_hf"), sums=bindparam("p_sums")), updates)
        self._pending_cache = new_cache

    def _committed_by_server(self, batch: _Batch) -> bool:
        """After a failure: did the batch commit anyway (reply lost)?  Raises if fenced or unreachable."""
        with self.db.engine.connect() as conn:
            cur = conn.execute(select(FrameCursor.batch_seq, FrameCursor.writer_token)
                               .where(FrameCursor.run_id == self.run_id)).first()
        if cur is None or cur.writer_token != self._token:
            raise WriterFenced(f"run {self.run_id}: another frame writer has taken this run over")
        return cur.batch_seq >= batch.seq

    def _done_locked(self, batch: _Batch) -> None:
        del self._chunks[:len(batch.chunks)]
        for name, rows in batch.rows.items():
            del self._rows[name][:len(rows)]
            self._n_rows -= len(rows)
            self._rows_committed += len(rows)
        self._inflight = None
        self._block_cache = self._pending_cache or {}
        self._pending_cache = None
        self._buffered_frames -= batch.frames
        self._committed_frames += batch.frames
        if batch.chunks:
            last = batch.chunks[-1]
            self._committed_index = last.first_index + last.count
        self._seq = batch.seq
        self._last_commit_wall = time.time()
        self._cond.notify_all()

    def _attempt(self, batch: _Batch) -> None:
        """Write ``batch`` once; on success mark it done.  On a transient failure the batch is kept
        as in flight and re-raised; any other failure makes the writer unusable."""
        if batch.empty:
            return
        try:
            if batch is self._inflight and self._committed_by_server(batch):
                self._pending_cache = None     # it did commit; re-read blocks from the database
            else:
                self._write(batch)
        except Exception as exc:          # noqa: BLE001 - classified here
            self._block_cache, self._pending_cache = {}, None      # the database is the truth again
            if _is_transient(exc):
                with self._cond:
                    self._inflight = batch
                self._note_failure(exc)
            else:
                self._set_fatal(exc)
            raise
        with self._cond:
            self._done_locked(batch)

    def _note_failure(self, exc: BaseException) -> None:
        with self._cond:
            self._retries += 1
            self._last_error = _short(exc)
            self._last_error_wall = time.time()
            self._cond.notify_all()
        log.warning("run %s: frame batch not written (%s); retrying", self.run_id, self._last_error)

    def _set_fatal(self, exc: BaseException) -> None:
        with self._cond:
            self._fatal = exc
            self._last_error = _short(exc)
            self._last_error_wall = time.time()
            self._cond.notify_all()
        log.error("run %s: frame writer stopped: %s", self.run_id, self._last_error)

    def _due_locked(self) -> bool:
        if self._closing or self._flush_requested:
            return True
        if self._buffered_frames - len(self._open) >= self.flush_frames:
            return True
        has_data = self._buffered_frames or self._n_rows
        return bool(has_data) and time.monotonic() - self._last_flush_mono >= self.flush_interval_s

    def _run(self) -> None:
        backoff = self.retry_initial_s
        while True:
            with self._cond:
                while not self._abandoned and self._inflight is None and not self._due_locked():
                    wait = self.flush_interval_s - (time.monotonic() - self._last_flush_mono)
                    self._cond.wait(timeout=max(wait, 0.01) if (self._buffered_frames or self._n_rows) else
                                    self.flush_interval_s)
                if self._abandoned:
                    return
                timed = time.monotonic() - self._last_flush_mono >= self.flush_interval_s
                batch = self._take_batch_locked(seal_open=timed or self._flush_requested or self._closing)
                self._last_flush_mono = time.monotonic()
                if batch.empty:
                    self._flush_requested = False
                    self._cond.notify_all()
                    if self._closing:
                        return
                    continue
            try:
                self._attempt(batch)
                backoff = self.retry_initial_s
            except Exception as exc:          # noqa: BLE001 - _attempt classified and recorded it
                if not _is_transient(exc):
                    return
                with self._cond:
                    if not self._abandoned:
                        self._cond.wait(timeout=backoff)
                backoff = min(backoff * 2, self.retry_max_s)

    # ------------------------------------------------------------------ control
    def flush(self, timeout: float | None = 30.0) -> None:
        """Write everything accepted so far (including the open chunk) and wait until committed.

        Raises ``StorageUnavailable`` if that does not happen within ``timeout`` wall seconds (the data
        stays buffered and is retried), or the writer's fatal error.  Gap rows still waiting to learn
        whether whole counter turns were lost are settled with the frames seen so far.
        """
        with self._cond:
            self._settle_turns()
        if self._thread is None:
            while True:
                with self._cond:
                    self._check_usable()
                    batch = self._take_batch_locked(seal_open=True)
                if batch.empty:
                    return
                try:
                    self._attempt(batch)
                except Exception as exc:          # noqa: BLE001
                    if _is_transient(exc):
                        raise StorageUnavailable(f"run {self.run_id}: batch not written: {_short(exc)}") from None
                    raise
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            target, rows_target = self._next_index, self._rows_queued
            self._flush_requested = True
            self._cond.notify_all()
            while not (self._committed_index >= target and self._rows_committed >= rows_target):
                if self._fatal is not None:
                    self._check_usable()
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise StorageUnavailable(f"run {self.run_id}: {self._buffered_frames} frames and {self._n_rows} "
                                             f"rows still buffered after {timeout} s ({self._last_error})")
                self._cond.wait(timeout=min(remaining, 1.0) if remaining is not None else 1.0)

    def close(self, timeout: float | None = 60.0) -> None:
        """Flush everything and stop the background thread.  Raises like ``flush`` when data is left."""
        if self._closed:
            return
        if self._thread is None:
            self.flush()
            self._closed = True
            return
        self.flush(timeout)
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join(timeout)
        self._closed = True

    def abandon(self) -> int:
        """Stop at once without writing what is buffered (what a crash does); returns the frames lost."""
        with self._cond:
            self._abandoned = True
            lost = self._buffered_frames
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(10)
        self._closed = True
        return lost

    def status(self) -> WriterStatus:
        """Counters of this writer (``live_writer_statuses()`` gives every writer of the process)."""
        with self._cond:
            return WriterStatus(run_id=self.run_id, next_index=self._next_index,
                                committed_frames=self._committed_frames, committed_index=self._committed_index,
                                buffered_frames=self._buffered_frames, buffered_rows=self._n_rows,
                                retries=self._retries, last_error=self._last_error,
                                last_error_wall=self._last_error_wall, last_commit_wall=self._last_commit_wall,
                                fatal=_short(self._fatal) if self._fatal else None, closed=self._closed)

    def __enter__(self) -> "FrameWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            try:
                self.close(timeout=10)
            except StorageError:
                log.exception("run %s: frame writer could not flush while handling %s", self.run_id, exc_type)

"""Storage of runs: SQLAlchemy 2 models, Alembic migrations, batched frame writer, readers, export.

Opening
-------
``open_database(url=None, *, schema=None) -> Database``
    ``url`` defaults to ``$BENCH_DATABASE_URL`` or ``sqlite:///var/bench.sqlite`` (CWD).  SQLite gets
    WAL, busy timeout, foreign keys and synchronous=FULL on every connection; PostgreSQL is used as
    ``postgresql+psycopg://user@host:port/db`` (``schema`` = own search_path).  The schema is
    upgraded to Alembic head programmatically (scripts ship in ``bench/storage/migrations``).
    ``Database``: ``.engine``, ``.sessionmaker``, ``.session()`` (transaction context manager),
    ``.dialect``, ``.size_bytes()``, ``.current_revision()``, ``.dispose()``.

Run bookkeeping (``bench.storage.queries``; each takes a ``Session``)
--------------------------------------------------------------------
``create_run(s, procedure=, parameters=, config_snapshot=, operator=, gyro_id=, bench_name=, start_at=)``,
``get_run``, ``list_runs``, ``set_run_status(s, run_id, status, error=, worker=)`` (state machine in
``TRANSITIONS``; raises ``InvalidTransition``), ``claim_next_run(s, worker)`` (queued + start_at due,
``SKIP LOCKED`` on PostgreSQL), ``heartbeat``, ``stale_runs``, ``save_checkpoint(s, run_id, checkpoint,
current_step=, progress=)``, ``add_steps``, ``set_step_status``, ``add_event``, ``list_events``,
``open_segment`` / ``close_segment`` / ``list_segments``, ``begin_suspension`` / ``end_suspension``,
``list_gaps``, ``frame_count``, ``ensure_gyro``, ``ensure_bench``, ``save_fits(s, gyro_id, run_ids,
results, accepted=) -> {model: version}``, ``accept_fits``, ``list_fits``.

Recording (``bench.storage.frames.FrameWriter``)
-----------------------------------------------
``FrameWriter(db, run_id, frame_kind="kvh_a", nominal_rate_hz=None, ...)``: ``add(frame)`` /
``add_many(frames)`` (GyroFrame, returns the index given), ``record_gap(t_from, t_to, reason,
frames_missing)``, ``add_probe_readings(t, readings)``, ``add_chamber(t, ChamberStatus)``,
``add_turntable(t, {axis: AxisState})``, ``add_psu(t, volts, amps, on)``, ``add_event(kind, message,
t_bench=, data=)``, ``add_segment(kind, t_start, t_end, temperature_c=, orientation=, ...)``,
``flush(timeout)``, ``close(timeout)``, ``abandon()`` (crash: drop the buffer), ``status() ->
WriterStatus`` (buffered_frames, buffered_rows, last_error, retries, healthy...).  Writes timed
batches from a background thread, buffers and retries through database outages, assigns per-run
indexes crash-safely, records sequence jumps and resumes as gaps.

Reading
-------
``read_frames(db, run_id, t_from=, t_to=, first_index=, last_index=) -> FrameArrays | None``,
``iter_frame_blocks(...)`` (streaming), ``iter_frames(...) -> StoredFrame(index, GyroFrame)``,
``second_means(db, run_id, t_from=, t_to=) -> SecondMeans`` (from per-second sums written at ingest).
Frame layouts are keyed by kind (``codec.register_frame_layout``; KVH Format A built in).

Export
------
``export_columns(db, run_id, resolution="second"|"frame") -> dict[str, np.ndarray]`` (time_s,
gyro_x/y/z in deg/h, temp_<probe>, chamber_pv/sp, orientation, power_w, ...),
``write_parquet(columns, path, metadata)``, ``export_parquet(db, run_id, path)``.

Errors: ``bench.storage.errors`` (StorageError, StorageUnavailable, BufferFull, WriterFenced,
UnknownRun, InvalidTransition, UnknownFrameKind), all ``bench.errors.BenchError``.
"""
from __future__ import annotations

from bench.storage.db import Database, default_url, migrate, open_database
from bench.storage.errors import (BufferFull, InvalidTransition, StorageError, StorageUnavailable, UnknownFrameKind,
                                  UnknownRun, WriterFenced)
from bench.storage.export import export_columns, export_parquet, write_parquet
from bench.storage.frames import FrameWriter, WriterStatus
from bench.storage.models import RunStatus
from bench.storage.reader import FrameArrays, SecondMeans, StoredFrame, iter_frame_blocks, iter_frames, read_frames, \
    second_means

__all__ = [
    "Database", "open_database", "default_url", "migrate",
    "FrameWriter", "WriterStatus", "FrameArrays", "SecondMeans", "StoredFrame",
    "read_frames", "iter_frame_blocks", "iter_frames", "second_means",
    "export_columns", "export_parquet", "write_parquet", "RunStatus",
    "StorageError", "StorageUnavailable", "BufferFull", "WriterFenced", "UnknownRun", "InvalidTransition",
    "UnknownFrameKind",
]

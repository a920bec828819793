"""Frame writer and readers on SQLite and PostgreSQL."""
from __future__ import annotations

import sqlite3
import threading
import time

import numpy as np
import pytest
from sqlalchemy import event, select
from sqlalchemy.exc import OperationalError

from bench.storage import (BufferFull, FrameWriter, StorageUnavailable, UnknownFrameKind, WriterFenced,
                           iter_frames, open_database, queries, read_frames, second_means)
from bench.storage.models import FrameChunk
from tests.test_storage_support import db, kvh_a_frame, make_frames, run_id  # noqa: F401 - fixtures


def _stored_indexes(db, run_id) -> np.ndarray:
    with db.engine.connect() as conn:
        rows = conn.execute(select(FrameChunk.first_index, FrameChunk.count).where(FrameChunk.run_id == run_id)
                            .order_by(FrameChunk.first_index)).all()
    return np.concatenate([np.arange(a, a + n) for a, n in rows]) if rows else np.zeros(0, np.int64)


def test_frames_round_trip_bit_exact_with_decoded_values(db, run_id):
    frames = make_frames(2500, seed=3)
    with FrameWriter(db, run_id, chunk_frames=1000, autostart=False) as w:
        assert w.add_many(frames) == 2499
    got = read_frames(db, run_id)
    assert got is not None and len(got) == 2500
    assert np.array_equal(got.index, np.arange(2500))
    assert all(got.raw_bytes(i) == f.raw for i, f in enumerate(frames))
    assert np.array_equal(got.gyro, np.array([f.gyro for f in frames]))
    assert np.array_equal(got.accel, np.array([f.accel for f in frames]))
    assert np.array_equal(got.sequence, [f.sequence for f in frames])
    assert np.allclose(got.temperature_c, [f.temperature_c for f in frames], atol=1e-9)
    assert np.max(np.abs(got.time - [f.host_time for f in frames])) <= 0.6e-6    # 1 us resolution
    # time and index windows
    part = read_frames(db, run_id, first_index=990, last_index=1010)
    assert list(part.index) == list(range(990, 1011))
    t_lo, t_hi = frames[100].host_time, frames[200].host_time
    win = read_frames(db, run_id, t_from=t_lo - 1e-7, t_to=t_hi + 1e-7)
    assert list(win.index) == list(range(100, 201))
    first = next(iter_frames(db, run_id, first_index=7, last_index=7))
    assert first.index == 7 and first.frame.raw == frames[7].raw and first.frame.gyro == frames[7].gyro


def test_writer_flushes_in_timed_batches_not_only_at_the_end(db, run_id):
    w = FrameWriter(db, run_id, flush_interval_s=0.1)
    try:
        w.add_many(make_frames(300))
        deadline = time.monotonic() + 5
        while w.status().committed_frames < 300 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert w.status().committed_frames == 300 and w.status().buffered_frames == 0
        assert len(_stored_indexes(db, run_id)) == 300      # visible to others while the writer is open
    finally:
        w.close()


def test_indexes_stay_monotonic_across_a_crash_and_the_resume_is_a_gap(db, run_id):
    frames = make_frames(3000, rate_hz=1000.0)
    w1 = FrameWriter(db, run_id, chunk_frames=400, autostart=False)
    w1.add_many(frames[:1000])
    w1.flush()
    w1.add_many(frames[1000:1500])       # accepted, never written: the process "dies"
    assert w1.abandon() == 500
    w2 = FrameWriter(db, run_id, chunk_frames=400, autostart=False, nominal_rate_hz=1000.0)
    assert w2.status().next_index == 1000
    assert w2.add_many(frames[2000:3000]) == 1999
    w2.close()
    idx = _stored_indexes(db, run_id)
    assert np.array_equal(idx, np.arange(2000))          # every index exactly once, no hole, no repeat
    got = read_frames(db, run_id)
    assert got.raw_bytes(999) == frames[999].raw and got.raw_bytes(1000) == frames[2000].raw
    with db.session() as s:
        gaps = queries.list_gaps(s, run_id)
    assert [(g.reason, g.after_index) for g in gaps] == [("crash_resume", 999)]
    assert gaps[0].t_from == pytest.approx(frames[999].host_time, abs=1e-6)
    assert gaps[0].t_to == pytest.approx(frames[2000].host_time, abs=1e-3)     # within a period
    assert gaps[0].frames_missing == 1000        # the stored last sequence number, wraps resolved by time


def test_sequence_jump_and_reported_link_gap_are_recorded(db, run_id):
    frames = make_frames(400, rate_hz=1000.0)
    kept = frames[:100] + frames[105:]              # 5 frames lost on the line
    with FrameWriter(db, run_id, autostart=False, nominal_rate_hz=1000.0) as w:
        w.add_many(kept)
        # a long outage: 300 frames missing, i.e. the 7-bit counter wrapped twice
        late = kvh_a_frame(frames[-1].host_time + 0.301, frames[-1].sequence + 301, (0.0, 0.0, 0.0))
        w.add(late)
        w.record_gap(frames[-1].host_time, late.host_time, "link_down")     # reported once frames are back
    with db.session() as s:
        gaps = [(g.reason, g.frames_missing, g.after_index) for g in queries.list_gaps(s, run_id)]
    assert gaps == [("corruption", 5, 99), ("link", 300, 394)]          # one row per outage, with its kind
    assert len(_stored_indexes(db, run_id)) == 396


def test_an_outage_reported_before_the_frames_return_is_one_row_counted_by_the_next_frame(db, run_id):
    frames = make_frames(600, rate_hz=1000.0)
    with FrameWriter(db, run_id, autostart=False, nominal_rate_hz=1000.0) as w:
        w.add_many(frames[:200])
        w.record_gap(frames[199].host_time, frames[450].host_time, "gyro link gap")
        w.add_many(frames[450:])
    with db.session() as s:
        gaps = [(g.reason, g.frames_missing, g.after_index) for g in queries.list_gaps(s, run_id)]
    assert gaps == [("link", 250, 199)]


def test_unreported_silences_count_their_hidden_turns_and_a_late_read_counts_none(db, run_id):
    """Nobody reports these outages: the counter shows only the loss modulo 128.  After a silent line
    (0.4 s, 3 s) the host stamps stay that far ahead of the counted time, so whole turns are counted;
    after a read 2 s late they fall back at the next prompt read, so none are."""
    truth = make_frames(12_000, rate_hz=1000.0)
    silent = set(range(2000, 2400)) | set(range(5000, 8000))
    kept = []
    for k, f in enumerate(truth):
        if k in silent:
            continue
        late = 2.0 if 10_000 <= k < 10_300 else 0.0        # these frames sat in a buffer 2 s
        kept.append(kvh_a_frame(f.host_time + late, f.sequence, f.gyro))
    with FrameWriter(db, run_id, autostart=False, nominal_rate_hz=1000.0) as w:
        w.add_many(kept)
    with db.session() as s:
        gaps = [(g.reason, g.frames_missing, g.after_index) for g in queries.list_gaps(s, run_id)]
    assert gaps == [("corruption", 400, 1999), ("link", 3000, 4599)]


def test_frames_read_in_one_burst_get_strictly_increasing_times_from_their_sequence(db, run_id):
    """The link stamps a whole read with one host time; stored times follow the counter and the rate
    (lost frames leave their period empty) and stay within a few periods of the host clock."""
    truth = make_frames(3000, rate_hz=1000.0)
    rng = np.random.default_rng(3)
    lost = set(rng.choice(3000, 300, replace=False).tolist()) - {0}
    burst = []
    for k, f in enumerate(truth):            # reads of 50 frames, each stamped at the read's end
        if k in lost:
            continue
        read_end = truth[min(2999, (k // 50) * 50 + 49)].host_time
        burst.append(kvh_a_frame(read_end, f.sequence, f.gyro))
    with FrameWriter(db, run_id, autostart=False, nominal_rate_hz=1000.0) as w:
        w.add_many(burst)
    got = read_frames(db, run_id)
    times = np.asarray(got.time)
    assert np.all(np.diff(times) > 0)
    true_t = np.array([truth[k].host_time for k in range(3000) if k not in lost])
    assert np.max(np.abs(times - true_t)) < 0.05
    with db.session() as s:
        assert sum(g.frames_missing for g in queries.list_gaps(s, run_id)) == len(lost)


def test_second_means_match_a_direct_computation_and_skip_invalid_frames(db, run_id):
    frames = make_frames(5000, rate_hz=1000.0, t0=1_700_000_000.25, seed=7)
    frames[1234] = kvh_a_frame(frames[1234].host_time, frames[1234].sequence, (50.0, 50.0, 50.0), status=0x73)
    # small chunks and many flushes so seconds are split across chunks and batches (upsert path)
    with FrameWriter(db, run_id, chunk_frames=300, autostart=False) as w:
        for i in range(0, 5000, 700):
            w.add_many(frames[i:i + 700])
            w.flush()
    sm = second_means(db, run_id)
    t = np.array([f.host_time for f in frames])
    g = np.array([f.gyro for f in frames])
    valid = np.array([f.status == 0x77 for f in frames])
    secs = np.floor(t).astype(int)
    assert list(sm.second) == sorted(set(secs))
    for k, sec in enumerate(sm.second):
        m = (secs == sec) & valid
        assert sm.n[k] == m.sum() and sm.n_invalid[k] == ((secs == sec) & ~valid).sum()
        assert np.allclose(sm.gyro[k], g[m].mean(axis=0), rtol=0, atol=1e-12)
        assert sm.time[k] == pytest.approx(t[m].mean(), abs=1e-6)
        assert sm.temperature_c[k] == pytest.approx(np.mean([f.temperature_c for f in frames if
                                                             np.floor(f.host_time) == sec]), abs=1e-9)
    assert sm.n_invalid.sum() == 1
    window = second_means(db, run_id, t_from=sm.second[1], t_to=sm.second[2] + 0.5)
    assert list(window.second) == list(sm.second[1:3])


def test_writer_buffers_through_an_outage_and_loses_nothing(tmp_path):
    path = tmp_path / "outage.sqlite"
    database = open_database(f"sqlite:///{path}", busy_timeout_ms=50)
    with database.session() as s:
        rid = queries.create_run(s, procedure="outage").id
    frames = make_frames(3000)
    w = FrameWriter(database, rid, flush_interval_s=0.05, retry_initial_s=0.02, retry_max_s=0.1)
    blocker = sqlite3.connect(path, timeout=0.05)
    try:
        w.add_many(frames[:1000])
        w.flush(5)
        blocker.execute("BEGIN EXCLUSIVE")           # the database is now unavailable to the writer
        w.add_many(frames[1000:2500])
        deadline = time.monotonic() + 5
        while w.status().retries < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        st = w.status()
        assert st.retries >= 2 and "locked" in (st.last_error or "") and not st.healthy
        assert st.buffered_frames == 1500 and st.committed_frames == 1000
        with pytest.raises(StorageUnavailable, match="still buffered"):
            w.flush(timeout=0.2)
        w.add_probe_readings(frames[1500].host_time, [])
        blocker.rollback()                           # back again
        w.add_many(frames[2500:])
        w.close(10)
        assert w.status().healthy and w.status().buffered_frames == 0
    finally:
        blocker.close()
    got = read_frames(database, rid)
    assert np.array_equal(got.index, np.arange(3000))
    assert all(got.raw_bytes(i) == f.raw for i, f in enumerate(frames))
    database.dispose()


def test_buffer_bound_refuses_frames_with_a_typed_error(tmp_path):
    database = open_database(f"sqlite:///{tmp_path / 'full.sqlite'}")
    with database.session() as s:
        rid = queries.create_run(s, procedure="full").id
    w = FrameWriter(database, rid, chunk_frames=10, max_buffered_frames=50, autostart=False)
    w.add_many(make_frames(50))
    with pytest.raises(BufferFull, match="50 frames buffered"):
        w.add(make_frames(1, t0=1_700_000_100.0)[0])
    assert w.status().next_index == 50               # the refused frame took no index
    w.close()
    database.dispose()


def test_a_lost_commit_reply_does_not_duplicate_the_batch(db, run_id):
    frames = make_frames(800)
    w = FrameWriter(db, run_id, chunk_frames=200, autostart=False)
    real_write = w._write
    calls = []

    def write_then_lose_reply(batch):
        real_write(batch)
        if not calls:
            calls.append(batch.seq)
            raise OperationalError("COMMIT", {}, Exception("server closed the connection unexpectedly"))

    w._write = write_then_lose_reply
    w.add_many(frames[:500])
    with pytest.raises(StorageUnavailable):
        w.flush()
    w.add_many(frames[500:])
    w.close()
    assert np.array_equal(_stored_indexes(db, run_id), np.arange(800))
    assert second_means(db, run_id).n.sum() == 800   # per-second sums not double-counted either


def test_a_second_writer_fences_off_the_first(db, run_id):
    frames = make_frames(200)
    w1 = FrameWriter(db, run_id, autostart=False)
    w1.add_many(frames[:100])
    w1.flush()
    w2 = FrameWriter(db, run_id, autostart=False)
    w1.add_many(frames[100:150])
    with pytest.raises(WriterFenced, match="another frame writer"):
        w1.flush()
    with pytest.raises(WriterFenced):
        w1.add(frames[150])
    w2.add_many(frames[100:])
    w2.close()
    assert np.array_equal(_stored_indexes(db, run_id), np.arange(200))


def test_a_batch_of_the_old_writer_racing_the_takeover_is_fenced_not_duplicated(tmp_path):
    """A takeover while the previous writer (a worker frozen past its lease, now woken) still writes: a
    batch the old writer tries while the new one opens is fenced, and the new one starts where the
    stored chunks end.  Deterministic on SQLite: the old writer's database gives up at once on a lock,
    and its batch is tried exactly while the new writer reads the run's chunks."""
    url = f"sqlite:///{tmp_path / 'race.sqlite'}"
    db = open_database(url)
    with db.session() as s:
        rid = queries.create_run(s, procedure="race").id
    old_db = open_database(url, busy_timeout_ms=0, migrate_to_head=False)
    frames = make_frames(200)
    w1 = FrameWriter(old_db, rid, autostart=False)
    w1.add_many(frames[:100])
    w1.flush()
    w1.add_many(frames[100:150])                 # the old writer's next batch, not yet written
    tried = []

    def old_writer_flushes(conn, cursor, statement, *_):
        if "FROM frame_chunks" in statement and not tried:     # the new writer reads where chunks end
            try:
                w1.flush()
                tried.append("stored")
            except (StorageUnavailable, WriterFenced) as exc:
                tried.append(type(exc).__name__)

    event.listen(db.engine, "before_cursor_execute", old_writer_flushes)
    try:
        w2 = FrameWriter(db, rid, autostart=False)
    finally:
        event.remove(db.engine, "before_cursor_execute", old_writer_flushes)
    assert tried == ["StorageUnavailable"]       # it waited for the lock the takeover holds
    with pytest.raises(WriterFenced, match="another frame writer"):
        w1.flush()
    w2.add_many(frames[100:])
    w2.close()
    assert np.array_equal(_stored_indexes(db, rid), np.arange(200))
    old_db.dispose()
    db.dispose()


def test_wrong_frame_length_and_unknown_kind_are_typed_errors(db, run_id):
    w = FrameWriter(db, run_id, autostart=False)
    bad = make_frames(1)[0]
    with pytest.raises(UnknownFrameKind, match="must be 36 bytes, got 35"):
        w.add(type(bad)(bad.host_time, bad.sequence, bad.gyro, bad.accel, bad.status, bad.temperature_c,
                        bad.raw[:35]))
    w.close()
    other = FrameWriter(db, run_id, frame_kind="mystery", autostart=False, sequence_modulus=None,
                        valid_status=None)
    other.add_many(make_frames(10))
    other.close()
    assert second_means(db, run_id).n.sum() == 10     # stored and summarised without a decoder
    with pytest.raises(UnknownFrameKind, match="'mystery'"):
        read_frames(db, run_id)


def test_concurrent_producer_and_reader(db, run_id):
    frames = make_frames(4000)
    w = FrameWriter(db, run_id, flush_interval_s=0.02, chunk_frames=250)
    stop = threading.Event()
    seen = []

    def reader():
        while not stop.is_set():
            fa = read_frames(db, run_id)
            seen.append(0 if fa is None else len(fa))
            time.sleep(0.01)

    t = threading.Thread(target=reader)
    t.start()
    try:
        for i in range(0, 4000, 100):
            w.add_many(frames[i:i + 100])
            time.sleep(0.002)
        w.close()
    finally:
        stop.set()
        t.join()
    assert seen == sorted(seen)                      # a reader only ever sees whole, growing prefixes
    assert np.array_equal(_stored_indexes(db, run_id), np.arange(4000))


def test_resonator_frequencies_are_summarised_and_frames_without_them_left_out(db, run_id):
    base = make_frames(400, rate_hz=100.0, t0=1_700_000_000.0)
    frames = []
    for k, f in enumerate(base):
        freq = None if k == 5 else (5000.0 + 0.01 * k, 5001.0, 5002.0)
        frames.append(type(f)(f.host_time, f.sequence, f.gyro, f.accel, f.status, f.temperature_c, f.raw, freq))
    with FrameWriter(db, run_id, autostart=False) as w:
        w.add_many(frames)
    sm = second_means(db, run_id)
    assert sm.freq_hz is not None and list(sm.n[:2]) == [99, 100] and sm.n_invalid[0] == 1
    expected = np.mean([5000.0 + 0.01 * k for k in range(100) if k != 5])
    assert sm.freq_hz[0, 0] == pytest.approx(expected, abs=1e-9)
    assert np.allclose(sm.freq_hz[:, 1], 5001.0)

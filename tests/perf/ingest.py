"""Storage benchmark: ``python -m tests.perf.ingest [--frames N] [--pg-url URL | --no-pg]``.

Measures, for SQLite (temp file) and PostgreSQL (a throw-away schema):

1. sustained ingest through ``FrameWriter`` (background thread, batches of 1000 frames as a link
   drain would hand them over) from the first ``add`` to the last commit, as a ratio to the
   2560 frames/s reference rate (targets: >= 40x SQLite, >= 20x PostgreSQL), next to a naive
   one-ORM-row-per-frame insert (``session.add`` per frame, commit per 1000) in the same run;
2. bytes on disk per frame (chunk + per-second summary + cursor tables, indexes and TOAST included)
   vs the 36 raw bytes (target <= 1.5x = 54 B), both for full chunks and for real-time pacing
   (1000 Hz frames flushed every 0.5 s -> 500-frame chunks, each second upserted twice);
3. time to read the 1-s means of a 24 h run recorded at 10 Hz (864 000 frames, 86 400 seconds;
   the read cost depends on the number of seconds, not frames), and for comparison the time to
   compute the same means by decoding every raw frame.

Frames are genuine KVH Format A frames (CRC-32/MPEG-2 computed, device-protocols.md 3.1) built with
numpy; building them is not timed.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from sqlalchemy import BigInteger, Float, Integer, LargeBinary, SmallInteger, UniqueConstraint, create_engine, text
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from bench.interfaces import GyroFrame
from bench.storage import FrameWriter, open_database, queries, read_frames, second_means
from bench.storage.codec import KVH_A_DTYPE

LINE_RATE_FPS = 2560.0
FRAME_BYTES = 36
FRAME_TABLES = ["frame_chunks", "frame_seconds", "frame_cursors"]
DEFAULT_PG = os.environ.get("BENCH_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


# ---------------------------------------------------------------- frame generation (not timed)
def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else crc << 1
        table[byte] = crc & 0xFFFFFFFF
    return table


_TABLE = _crc_table()


def crc32_mpeg2_rows(body: np.ndarray) -> np.ndarray:
    """CRC-32/MPEG-2 of every row of a (n, 32) uint8 array, vectorised over rows."""
    crc = np.full(body.shape[0], 0xFFFFFFFF, dtype=np.uint32)
    for j in range(body.shape[1]):
        crc = (crc << np.uint32(8)) ^ _TABLE[((crc >> np.uint32(24)) ^ body[:, j]) & 0xFF]
    return crc


def frame_blocks(n: int, *, rate_hz: float, t0: float = 1_700_000_000.0, block: int = 20_000,
                 seed: int = 5) -> Iterator[list[GyroFrame]]:
    """``n`` Format A frames at ``rate_hz`` in lists of ``block`` (random-walk bias + white noise)."""
    rng = np.random.default_rng(seed)
    for start in range(0, n, block):
        m = min(block, n - start)
        i = np.arange(start, start + m)
        rec = np.zeros(m, dtype=KVH_A_DTYPE)
        rec["header"] = 0xFE81FF55
        rec["gyro"] = rng.normal(0, 0.02, (m, 3)) + [0.0041, -0.0017, 0.0043]
        rec["accel"] = rng.normal(0, 0.002, (m, 3)) + [0.0, 0.0, 1.0]
        rec["status"] = 0x77
        rec["sequence"] = i % 128
        rec["temp_raw"] = 2500 + (i // 5000) % 500
        raw = rec.view(np.uint8).reshape(m, 36)
        rec["crc"] = crc32_mpeg2_rows(raw[:, :32])
        raw = rec.view(np.uint8).reshape(m, 36)
        gyro = rec["gyro"].astype(float).tolist()
        accel = rec["accel"].astype(float).tolist()
        temps = (rec["temp_raw"] / 100.0).tolist()
        times = (t0 + i / rate_hz + rng.uniform(0, 1e-4, m)).tolist()
        yield [GyroFrame(times[k], k_seq, tuple(gyro[k]), tuple(accel[k]), 0x77, temps[k], raw[k].tobytes())
               for k, k_seq in enumerate((i % 128).tolist())]


# ---------------------------------------------------------------- naive baseline
class _NaiveBase(DeclarativeBase):
    pass


class NaiveFrame(_NaiveBase):
    __tablename__ = "naive_frames"
    __table_args__ = (UniqueConstraint("run_id", "frame_index"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int]
    frame_index: Mapped[int] = mapped_column(BigInteger)
    t: Mapped[float] = mapped_column(Float(53))
    gx: Mapped[float] = mapped_column(Float(53))
    gy: Mapped[float] = mapped_column(Float(53))
    gz: Mapped[float] = mapped_column(Float(53))
    ax: Mapped[float] = mapped_column(Float(53))
    ay: Mapped[float] = mapped_column(Float(53))
    az: Mapped[float] = mapped_column(Float(53))
    status: Mapped[int] = mapped_column(SmallInteger)
    seq: Mapped[int] = mapped_column(SmallInteger)
    temp: Mapped[float] = mapped_column(Float(53))
    raw: Mapped[bytes] = mapped_column(LargeBinary)


def naive_ingest(db, frames: list[GyroFrame]) -> tuple[float, float]:
    """(frames/s, bytes/frame) of one ORM object per frame, commit every 1000 frames."""
    _NaiveBase.metadata.create_all(db.engine)
    t_start = time.perf_counter()
    with Session(db.engine) as s:
        for k, f in enumerate(frames):
            s.add(NaiveFrame(run_id=1, frame_index=k, t=f.host_time, gx=f.gyro[0], gy=f.gyro[1], gz=f.gyro[2],
                             ax=f.accel[0], ay=f.accel[1], az=f.accel[2], status=f.status, seq=f.sequence,
                             temp=f.temperature_c, raw=f.raw))
            if k % 1000 == 999:
                s.commit()
        s.commit()
    rate = len(frames) / (time.perf_counter() - t_start)
    return rate, db.tables_size_bytes(["naive_frames"]) / len(frames)


# ---------------------------------------------------------------- measurements
def _new_run(db) -> int:
    with db.session() as s:
        return queries.create_run(s, procedure="perf", config_snapshot={"gyro": {"output_units": "deg/s"}}).id


def writer_ingest(db, n: int, rate_hz: float = 1000.0) -> float:
    """Frames/s through the background writer (blocks of 1000 frames, until all is committed)."""
    run = _new_run(db)
    blocks = list(frame_blocks(n, rate_hz=rate_hz))
    w = FrameWriter(db, run, nominal_rate_hz=rate_hz)
    t_start = time.perf_counter()
    for big in blocks:
        for k in range(0, len(big), 1000):
            w.add_many(big[k:k + 1000])
    w.close(600)
    elapsed = time.perf_counter() - t_start
    assert w.status().committed_frames == n
    return n / elapsed


def paced_size(db, n: int, rate_hz: float = 1000.0, flush_every_s: float = 0.5) -> int:
    """Bytes/frame of the frame tables when frames arrive in real time (flush every 0.5 s of frames)."""
    run = _new_run(db)
    per_flush = max(1, int(rate_hz * flush_every_s))
    with FrameWriter(db, run, autostart=False, nominal_rate_hz=rate_hz) as w:
        for big in frame_blocks(n, rate_hz=rate_hz, t0=1_800_000_000.0):
            for k in range(0, len(big), per_flush):
                w.add_many(big[k:k + per_flush])
                w.flush()
    return run


def frame_table_bytes(db) -> int:
    return db.tables_size_bytes(FRAME_TABLES)


def day_read(db, rate_hz: float = 10.0, hours: float = 24.0) -> dict[str, float]:
    n = int(rate_hz * hours * 3600)
    run = _new_run(db)
    t_start = time.perf_counter()
    with FrameWriter(db, run, nominal_rate_hz=rate_hz) as w:
        for big in frame_blocks(n, rate_hz=rate_hz, t0=1_900_000_000.0, block=50_000):
            w.add_many(big)
    write_s = time.perf_counter() - t_start
    if db.dialect == "postgresql":
        with db.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            conn.exec_driver_sql("VACUUM ANALYZE frame_seconds")
            conn.exec_driver_sql("VACUUM ANALYZE frame_chunks")
    second_means(db, run)          # warm the cache once, as a UI would after the first load
    reads = []
    for _ in range(3):
        t0 = time.perf_counter()
        sm = second_means(db, run)
        reads.append(time.perf_counter() - t0)
    assert len(sm) == int(hours * 3600) and int(sm.n.sum()) == n
    t0 = time.perf_counter()
    fa = read_frames(db, run)
    secs = np.floor(fa.time).astype(np.int64)
    uniq, inv = np.unique(secs, return_inverse=True)
    means = np.stack([np.bincount(inv, weights=fa.gyro[:, i]) for i in range(3)], axis=1) / \
        np.bincount(inv)[:, None]
    decode_s = time.perf_counter() - t0
    assert np.allclose(means, sm.gyro, atol=1e-9)
    return {"frames": n, "seconds": len(sm), "write_s": write_s, "read_s": min(reads), "decode_all_s": decode_s}


def run_backend(name: str, db, n: int, naive_n: int) -> dict[str, float]:
    out: dict[str, float] = {}
    out["writer_fps"] = writer_ingest(db, n)
    size_full = frame_table_bytes(db)
    out["bytes_per_frame_full"] = size_full / n
    paced_size(db, min(n, 200_000))
    size_paced = frame_table_bytes(db) - size_full
    out["bytes_per_frame_paced"] = size_paced / min(n, 200_000)
    if db.dialect == "postgresql":
        with db.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            conn.exec_driver_sql("VACUUM frame_seconds")
        out["bytes_per_frame_paced_vacuumed"] = (frame_table_bytes(db) - size_full) / min(n, 200_000)
    naive_frames = [f for b in frame_blocks(naive_n, rate_hz=1000.0, t0=1_600_000_000.0) for f in b]
    out["naive_fps"], out["naive_bytes_per_frame"] = naive_ingest(db, naive_frames)
    out.update({f"day_{k}": v for k, v in day_read(db).items()})
    return out


def report(name: str, r: dict[str, float], target_ratio: float) -> None:
    print(f"\n== {name} ==")
    print(f"ingest (FrameWriter)     : {r['writer_fps']:>10,.0f} frames/s = {r['writer_fps'] / LINE_RATE_FPS:6.1f}x "
          f"2560 (target >= {target_ratio:.0f}x) {'OK' if r['writer_fps'] / LINE_RATE_FPS >= target_ratio else 'MISS'}")
    print(f"ingest (naive ORM/frame) : {r['naive_fps']:>10,.0f} frames/s = {r['naive_fps'] / LINE_RATE_FPS:6.1f}x "
          f"2560   ({r['writer_fps'] / r['naive_fps']:.0f}x slower than the writer)")
    for key, label in (("bytes_per_frame_full", "full 1000-frame chunks"),
                       ("bytes_per_frame_paced", "real-time 0.5 s flushes"),
                       ("bytes_per_frame_paced_vacuumed", "real-time, after VACUUM")):
        if key in r:
            v = r[key]
            print(f"bytes/frame {label:<24}: {v:6.1f} B = {v / FRAME_BYTES:4.2f}x 36 B (target <= 1.5x) "
                  f"{'OK' if v <= 1.5 * FRAME_BYTES else 'MISS'}")
    print(f"bytes/frame naive table  : {r['naive_bytes_per_frame']:6.1f} B = {r['naive_bytes_per_frame'] / 36:4.2f}x")
    print(f"24 h run @10 Hz: {r['day_frames']:,.0f} frames, {r['day_seconds']:,.0f} s; written in {r['day_write_s']:.1f} s; "
          f"1-s means read in {r['day_read_s'] * 1000:.0f} ms (target < 1000 ms) "
          f"{'OK' if r['day_read_s'] < 1.0 else 'MISS'}; same means by decoding every raw frame: "
          f"{r['day_decode_all_s'] * 1000:.0f} ms")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000, help="frames for the ingest measurement")
    ap.add_argument("--naive-frames", type=int, default=20_000)
    ap.add_argument("--pg-url", default=DEFAULT_PG)
    ap.add_argument("--no-pg", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        db = open_database(f"sqlite:///{Path(tmp) / 'perf.sqlite'}")
        report("SQLite", run_backend("sqlite", db, args.frames, args.naive_frames), 40)
        db.dispose()
    if args.no_pg:
        return
    schema = f"perf_{uuid.uuid4().hex[:8]}"
    db = open_database(args.pg_url, schema=schema)
    try:
        report("PostgreSQL", run_backend("postgresql", db, args.frames, args.naive_frames), 20)
    finally:
        db.dispose()
        eng = create_engine(args.pg_url)
        with eng.begin() as conn:
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        eng.dispose()


if __name__ == "__main__":
    main()

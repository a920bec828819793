"""Drill: frames keep flowing into PostgreSQL while the server restarts; nothing may be lost or doubled.

``python -m tests.perf.pg_restart_drill [--seconds 20] [--rate 2000] [--restart-at 6] [--down-s X]``
(not part of the test suite: it restarts the local cluster with
``pg_ctlcluster --skip-systemctl-redirect <version> main restart``, which disturbs anyone else using it).
A plain restart is often shorter than one flush interval, so the writer may not even notice it;
``--down-s X`` stops the cluster, waits X seconds and starts it, forcing the buffer-and-retry path
(the drill then also requires that the writer saw the outage).

A producer thread adds genuine KVH Format A frames to a ``FrameWriter`` at ``--rate`` frames/s of
wall time; mid-run the cluster is restarted.  Afterwards every frame index 0..N-1 must be stored
exactly once, each with the raw bytes that were added under that index, and the per-second sums
must count N frames.  Prints the writer status seen during the outage and exits 1 on any failure.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
from sqlalchemy import create_engine, select, text

from bench.storage import FrameWriter, open_database, queries, second_means
from bench.storage.models import FrameChunk
from tests.perf.ingest import DEFAULT_PG, frame_blocks


def _ctl(action: str) -> None:
    versions = sorted(os.listdir("/etc/postgresql"))
    if len(versions) != 1:
        raise SystemExit(f"expected one PostgreSQL version under /etc/postgresql, found {versions}")
    subprocess.run(["pg_ctlcluster", "--skip-systemctl-redirect", versions[0], "main", action], check=True)


def restart_cluster(down_s: float | None) -> float:
    t0 = time.monotonic()
    if down_s is None:
        _ctl("restart")
    else:
        _ctl("stop")
        time.sleep(down_s)
        _ctl("start")
    return time.monotonic() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=2000.0, help="frames per wall second")
    ap.add_argument("--restart-at", type=float, default=6.0)
    ap.add_argument("--down-s", type=float, default=None, help="stop, wait this long, start (instead of restart)")
    ap.add_argument("--pg-url", default=DEFAULT_PG)
    args = ap.parse_args(argv)

    n = int(args.seconds * args.rate)
    frames = [f for b in frame_blocks(n, rate_hz=args.rate) for f in b]
    schema = f"drill_{uuid.uuid4().hex[:8]}"
    db = open_database(args.pg_url, schema=schema)
    with db.session() as s:
        run = queries.create_run(s, procedure="pg_restart_drill").id
    writer = FrameWriter(db, run, nominal_rate_hz=args.rate, flush_interval_s=0.5, retry_initial_s=0.1,
                         retry_max_s=1.0)
    worst = {"buffered": 0, "error": None, "retries": 0}
    done = threading.Event()

    def produce() -> None:
        step = max(1, int(args.rate / 50))            # 20 ms worth of frames per add, like a link drain
        t_start = time.monotonic()
        for k in range(0, n, step):
            delay = t_start + k / args.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            writer.add_many(frames[k:k + step])
        done.set()

    def watch() -> None:
        while not done.is_set():
            st = writer.status()
            if st.buffered_frames > worst["buffered"]:
                worst["buffered"] = st.buffered_frames
            if st.last_error:
                worst["error"] = st.last_error
            worst["retries"] = st.retries
            time.sleep(0.05)

    producer = threading.Thread(target=produce)
    watcher = threading.Thread(target=watch, daemon=True)
    producer.start()
    watcher.start()
    time.sleep(args.restart_at)
    how = "restarting" if args.down_s is None else f"stopping for {args.down_s:.1f} s"
    print(f"{how} PostgreSQL at t={args.restart_at:.1f} s "
          f"(committed so far: {writer.status().committed_frames} frames)")
    took = restart_cluster(args.down_s)
    print(f"cluster back after {took:.2f} s")
    producer.join()
    writer.close(timeout=120)
    st = writer.status()
    print(f"during the outage: max buffered {worst['buffered']} frames, {st.retries} failed attempts, "
          f"last error: {worst['error']}")

    ok = True
    with db.engine.connect() as conn:
        rows = conn.execute(select(FrameChunk.first_index, FrameChunk.count, FrameChunk.raw)
                            .where(FrameChunk.run_id == run).order_by(FrameChunk.first_index)).all()
    idx = np.concatenate([np.arange(a, a + c) for a, c, _ in rows])
    counts = np.bincount(idx, minlength=n)
    if len(idx) != n or not np.all(counts == 1):
        ok = False
        print(f"FAIL: {len(idx)} stored for {n} added; missing {np.sum(counts == 0)}, doubled {np.sum(counts > 1)}")
    raw = b"".join(r for _, _, r in rows)
    if raw != b"".join(f.raw for f in frames):
        ok = False
        print("FAIL: stored raw bytes differ from the frames added (order or content)")
    total = int(second_means(db, run).n.sum())
    if total != n:
        ok = False
        print(f"FAIL: per-second sums count {total} frames, expected {n}")
    if worst["error"] is None:
        print("note: the writer never saw an error (the restart fitted between two flushes)")
        if args.down_s is not None:
            ok = False
            print("FAIL: a stopped server must show up as an outage")
    print(f"{'PASS' if ok else 'FAIL'}: {n} frames added, {len(idx)} stored, indexes 0..{n - 1} each exactly once, "
          f"raw bytes identical, per-second sums count {total}")
    db.dispose()
    eng = create_engine(args.pg_url)
    with eng.begin() as conn:
        conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
    eng.dispose()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

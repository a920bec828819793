"""GET /gyros/{id}/coefficients latency with 10,000 gyros stored, at 200 requests/s from a second process.

    .venv/bin/python tests/perf/api_latency.py [--gyros 10000] [--rate 200] [--seconds 10] [--db URL]

1. Fills a fresh database (default: an SQLite file in a temp dir; ``--db`` for PostgreSQL) with N gyros,
   each with one accepted ``static`` fit (x, y, z rows as the fitting module stores them: coefficients,
   units, validity, definition), plus a few older unaccepted versions.
2. Starts the API (uvicorn, one process) on loopback.
3. A second process sends requests open-loop at a fixed rate (a request is due every 1/rate s, whether
   or not the previous one has answered; several connections), each for a random gyro, and measures
   each latency from its *scheduled* send time (no coordinated omission).
4. Prints count, errors, achieved rate, p50 / p95 / p99 / max in ms; target p99 <= 20 ms.

``--record``: meanwhile a third process records a run on the same database (``bench run thermal_ramp
--sim --speed 3600``: the simulated bench, its worker engine and the frame writer); the measurement
starts once its frames are being stored, and the frames stored during it are printed.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
TOKEN = "perf-viewer-token"


def fill(db_url: str, n_gyros: int) -> None:
    import numpy as np
    from sqlalchemy import insert

    from bench.fit.base import Dataset
    from bench.fit.catalog import fit_model
    from bench.storage import open_database
    from bench.storage.models import Fit, Gyro, utcnow

    db = open_database(db_url)
    rng = np.random.default_rng(0)
    t = np.arange(1200.0)
    temp = 10 + 30 * (0.5 - 0.5 * np.cos(2 * np.pi * t / 1200))
    cols = {"time_s": t, "temp_t1": temp}
    for ch in "xyz":
        cols[f"gyro_{ch}"] = 2.0 + 0.3 * (temp - 25) + rng.normal(0, 0.05, t.size)
    template = {ch: fit_model("static", Dataset(cols, {}), ch).to_json() for ch in "xyz"}
    now = utcnow()
    gyros, fits = [], []
    for i in range(n_gyros):
        gid = f"RLG-{i:05d}"
        gyros.append({"gyro_id": gid, "type": "RLG", "notes": ""})
        versions = 1 + (i % 3)
        for v in range(1, versions + 1):
            for ch in "xyz":
                res = dict(template[ch])
                coeffs = {k: val * (1 + 0.01 * rng.standard_normal()) for k, val in res["coefficients"].items()}
                res["coefficients"] = coeffs
                fits.append({"gyro_id": gid, "run_ids": [i + 1], "model": "static", "channel": ch, "version": v,
                             "coefficients": coeffs, "result": res, "created_at": now, "accepted": v == versions})
    with db.engine.begin() as conn:
        for k in range(0, len(gyros), 5000):
            conn.execute(insert(Gyro), gyros[k:k + 5000])
        for k in range(0, len(fits), 5000):
            conn.execute(insert(Fit), fits[k:k + 5000])
    db.dispose()
    print(f"stored {n_gyros} gyros, {len(fits)} fit rows")


def load(port: int, n_gyros: int, rate: float, seconds: float, out: mp.Queue) -> None:
    """The client process: open-loop schedule, a pool of threads with keep-alive connections (plain
    http.client: a heavier client library's own per-request cost would be counted as server latency)."""
    import http.client

    total = int(rate * seconds)
    start = time.perf_counter() + 0.5
    latencies: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()
    next_i = [0]
    rnd = random.Random(1)
    ids = [f"RLG-{rnd.randrange(n_gyros):05d}" for _ in range(total)]

    def worker() -> None:
        client = http.client.HTTPConnection("127.0.0.1", port, timeout=5.0)
        headers = {"Authorization": f"Bearer {TOKEN}"}
        try:
            while True:
                with lock:
                    i = next_i[0]
                    next_i[0] += 1
                if i >= total:
                    return
                due = start + i / rate
                delay = due - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                try:
                    client.request("GET", f"/gyros/{ids[i]}/coefficients", headers=headers)
                    r = client.getresponse()
                    body = r.read()
                    ok = r.status == 200 and json.loads(body)["models"][0]["accepted"]
                except Exception as exc:  # noqa: BLE001 - counted as an error
                    ok, r = False, exc
                    client.close()
                lat = time.perf_counter() - due
                with lock:
                    latencies.append(lat)
                    if not ok:
                        errors.append(str(getattr(r, "status", r)))
        finally:
            client.close()

    threads = [threading.Thread(target=worker) for _ in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    out.put((latencies, errors, time.perf_counter() - start))


def _frames_stored(db_url: str) -> int:
    from sqlalchemy import func, select

    from bench.storage import open_database
    from bench.storage.models import FrameCursor

    db = open_database(db_url)
    try:
        with db.session() as s:
            return int(s.scalar(select(func.coalesce(func.sum(FrameCursor.next_index), 0))))
    finally:
        db.dispose()


def _wait_recording(db_url: str, recorder: subprocess.Popen) -> int:
    """Wait until the recording run stores frames; returns the count stored then."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if recorder.poll() is not None:
            raise SystemExit(f"the recording run exited ({recorder.returncode}) before storing frames")
        n = _frames_stored(db_url)
        if n > 0:
            return n
        time.sleep(0.5)
    raise SystemExit("the recording run stored no frame within 120 s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gyros", type=int, default=10_000)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--db", default=None, help="database URL (default: a fresh SQLite file)")
    ap.add_argument("--record", action="store_true", help="a run records at x3600 on the same database meanwhile")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="api-latency-"))
    db_url = args.db or f"sqlite:///{tmp / 'perf.sqlite'}"
    fill(db_url, args.gyros)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "BENCH_DATABASE_URL": db_url, "BENCH_TOKENS": f"viewer:{TOKEN}", "PYTHONPATH": str(ROOT)}
    server = subprocess.Popen([sys.executable, "-m", "uvicorn", "--factory", "api.app:app_from_env", "--port",
                               str(port), "--log-level", "warning", "--no-access-log", "--loop", "uvloop",
                               "--http", "httptools"], env=env, cwd=tmp)
    recorder = None
    try:
        import httpx
        if args.record:
            recorder = subprocess.Popen([sys.executable, "-m", "bench", "run", "thermal_ramp", "--gyro", "PERF-REC",
                                         "--sim", "--speed", "3600", "--param", "soak_h=30", "--param", "end_c=-30",
                                         "--param", "rate_c_per_min=0.5"], env=env, cwd=tmp,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            frames_before = _wait_recording(db_url, recorder)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        # warm-up (connection pool, SQLite page cache)
        with httpx.Client(headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            for i in range(200):
                c.get(f"http://127.0.0.1:{port}/gyros/RLG-{i:05d}/coefficients")
        q: mp.Queue = mp.get_context("spawn").Queue()
        client = mp.get_context("spawn").Process(target=load, args=(port, args.gyros, args.rate, args.seconds, q))
        client.start()
        latencies, errors, elapsed = q.get(timeout=args.seconds * 10 + 60)
        client.join()
        if recorder is not None:
            if recorder.poll() is not None:
                raise SystemExit("the recording run ended before the measurement did: lengthen it")
            recorded = _frames_stored(db_url) - frames_before
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=10)
        if recorder is not None and recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
            try:
                recorder.wait(timeout=30)
            except subprocess.TimeoutExpired:
                recorder.kill()
    lat = sorted(x * 1000 for x in latencies)

    def pct(p: float) -> float:
        return lat[min(len(lat) - 1, int(round(p / 100 * (len(lat) - 1))))]

    doc = {"gyros": args.gyros, "requests": len(lat), "errors": len(errors), "rate_target": args.rate,
           "rate_achieved": round(len(lat) / elapsed, 1), "p50_ms": round(pct(50), 2), "p95_ms": round(pct(95), 2),
           "p99_ms": round(pct(99), 2), "max_ms": round(lat[-1], 2), "database": db_url.split(":")[0],
           "target_p99_ms": 20.0}
    if args.record:
        doc["frames_recorded_meanwhile"] = recorded
    print(json.dumps(doc))
    print(f"p99 = {doc['p99_ms']} ms at {doc['rate_achieved']} req/s over {args.gyros} gyros "
          f"({'meets' if doc['p99_ms'] <= 20 and not errors else 'MISSES'} the 20 ms target)")


if __name__ == "__main__":
    main()

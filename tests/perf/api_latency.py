"""GET /gyros/{id}/coefficients latency with 10,000 gyros stored, stepping the request rate from a second process.

    .venv/bin/python tests/perf/api_latency.py [--gyros 10000] [--rates 25,50,...] [--seconds 10] [--db URL]
        [--record] [--api-workers N]

1. Fills a fresh database (default: an SQLite file in a temp dir; ``--db`` for PostgreSQL) with N gyros,
   each with one accepted ``static`` fit (x, y, z rows as the fitting module stores them: coefficients,
   units, validity, definition), plus a few older unaccepted versions.
2. Starts the API (uvicorn, ``--api-workers`` processes) on loopback.
3. A second process sends requests open-loop at a fixed rate (a request is due every 1/rate s, whether
   or not the previous one has answered; several connections), each for a random gyro, and measures
   each latency from its *scheduled* send time (no coordinated omission).
4. Steps through the rates (ascending), printing per step the achieved rate, p50 / p95 / p99 / max in ms
   and the 1-min load average (stopping once the server is saturated: the rate not achieved or p99 over
   1 s), and prints the highest rate that kept p99 <= 20 ms without errors.

``--record``: meanwhile a third process records a run on the same database (``bench run thermal_ramp
--sim --speed 3600``: the simulated bench, its worker engine and the frame writer); the measurement
starts once its frames are being stored, and the frames stored during each step are printed.
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


def _measure(port: int, n_gyros: int, rate: float, seconds: float) -> dict:
    """One step: the load process at ``rate`` for ``seconds``; latency percentiles, achieved rate, load."""
    load_before = os.getloadavg()[0]
    q: mp.Queue = mp.get_context("spawn").Queue()
    client = mp.get_context("spawn").Process(target=load, args=(port, n_gyros, rate, seconds, q))
    client.start()
    latencies, errors, elapsed = q.get(timeout=seconds * 10 + 60)
    client.join()
    lat = sorted(x * 1000 for x in latencies)

    def pct(p: float) -> float:
        return lat[min(len(lat) - 1, int(round(p / 100 * (len(lat) - 1))))]

    doc = {"rate_target": rate, "rate_achieved": round(len(lat) / elapsed, 1), "requests": len(lat),
           "errors": len(errors), "p50_ms": round(pct(50), 2), "p95_ms": round(pct(95), 2),
           "p99_ms": round(pct(99), 2), "max_ms": round(lat[-1], 2),
           "load_avg_1min": round((load_before + os.getloadavg()[0]) / 2, 2)}
    doc["meets"] = (doc["p99_ms"] <= TARGET_P99_MS and not errors and doc["rate_achieved"] >= 0.95 * rate)
    return doc


TARGET_P99_MS = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gyros", type=int, default=10_000)
    ap.add_argument("--rates", default="25,50,100,150,200,300,400",
                    help="request rates to step through, ascending; the steps stop at the first that misses")
    ap.add_argument("--rate", type=float, default=None, help="one rate only (instead of --rates)")
    ap.add_argument("--seconds", type=float, default=10.0, help="per step")
    ap.add_argument("--api-workers", type=int, default=1, help="uvicorn worker processes")
    ap.add_argument("--db", default=None, help="database URL (default: a fresh SQLite file)")
    ap.add_argument("--record", action="store_true", help="a run records at x3600 on the same database meanwhile")
    args = ap.parse_args()
    rates = [args.rate] if args.rate else sorted(float(r) for r in args.rates.split(","))
    tmp = Path(tempfile.mkdtemp(prefix="api-latency-"))
    db_url = args.db or f"sqlite:///{tmp / 'perf.sqlite'}"
    fill(db_url, args.gyros)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "BENCH_DATABASE_URL": db_url, "BENCH_TOKENS": f"viewer:{TOKEN}", "PYTHONPATH": str(ROOT)}
    server = subprocess.Popen([sys.executable, "-m", "uvicorn", "--factory", "api.app:app_from_env", "--port",
                               str(port), "--log-level", "warning", "--no-access-log", "--loop", "uvloop",
                               "--http", "httptools", "--workers", str(args.api_workers)], env=env, cwd=tmp)
    recorder = None
    steps = []
    try:
        import httpx
        if args.record:
            recorder = subprocess.Popen([sys.executable, "-m", "bench", "run", "thermal_ramp", "--gyro", "PERF-REC",
                                         "--sim", "--speed", "3600", "--param", "soak_h=30", "--param", "end_c=-30",
                                         "--param", "rate_c_per_min=0.5"], env=env, cwd=tmp,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            _wait_recording(db_url, recorder)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        # warm-up (connection pool, SQLite page cache; every worker process)
        with httpx.Client(headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            for i in range(200 * args.api_workers):
                c.get(f"http://127.0.0.1:{port}/gyros/RLG-{i:05d}/coefficients")
        for rate in rates:
            frames_before = _frames_stored(db_url) if recorder is not None else 0
            step = _measure(port, args.gyros, rate, args.seconds)
            if recorder is not None:
                if recorder.poll() is not None:
                    raise SystemExit("the recording run ended before the measurement did: lengthen it")
                step["frames_recorded_meanwhile"] = _frames_stored(db_url) - frames_before
            steps.append(step)
            print(json.dumps(step), flush=True)
            if step["rate_achieved"] < 0.95 * rate or step["p99_ms"] > 50 * TARGET_P99_MS:
                break                          # saturated: higher rates only queue longer
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=10)
        if recorder is not None and recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
            try:
                recorder.wait(timeout=30)
            except subprocess.TimeoutExpired:
                recorder.kill()
    best = max((st["rate_achieved"] for st in steps if st["meets"]), default=None)
    summary = {"gyros": args.gyros, "database": db_url.split(":")[0], "api_workers": args.api_workers,
               "recording": args.record, "target_p99_ms": TARGET_P99_MS, "highest_rate_meeting_target": best,
               "steps": len(steps)}
    print(json.dumps(summary))
    print(f"highest rate with p99 <= {TARGET_P99_MS:g} ms: "
          f"{f'{best} req/s' if best is not None else 'none of the rates stepped'} over {args.gyros} gyros"
          f"{' while a run records at x3600' if args.record else ''}")


if __name__ == "__main__":
    main()

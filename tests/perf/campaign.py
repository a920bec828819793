"""Benchmark: the full default ``eight_position`` campaign (S000 3.2, about 46 h of bench time) on the
simulated bench, timed on the wall.

``python -m tests.perf.campaign [--speed 3600] [--mode process|inprocess] [--db URL] [--keep]``

* ``--mode process`` (default): the simulated bench runs in its own process (``bench sim up
  --endpoints-json F``, so its gyro physics has a CPU core and a GIL of its own) and the run attaches
  to it with ``bench run eight_position --sim-endpoints F``.
* ``--mode inprocess``: ``bench run eight_position --sim`` (simulator threads share the run's process).

The gyro data rate is the simulated bench's default for the speed (``bench.sim.bench.default_data_rate``:
1 Hz up to x5000); engine ticks follow ``bench.engine.factory.engine_config_for`` (fine tick 0.02 wall
s, soak tick 0.1 wall s, telemetry every 0.05 wall s, checkpoint every 0.5 wall s).  Database: a fresh
SQLite file unless ``--db``.  Prints the wall time of the run (start of ``bench run`` to its end), the
bench hours covered, frames stored, frames expected at the data rate, gaps and suspensions, and exits
1 when the run did not complete, lost frames (sequence gaps / overruns) or took longer than
``--budget-s`` (120).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _wait_file(path: Path, proc: subprocess.Popen, timeout_s: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"bench sim up exited early: {proc.stderr.read().decode()[-2000:]}")
        if path.exists():
            return json.loads(path.read_text())
        time.sleep(0.1)
    raise SystemExit("bench sim up did not write its endpoints in time")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=3600.0)
    ap.add_argument("--mode", choices=("process", "inprocess"), default="process")
    ap.add_argument("--db", default=None)
    ap.add_argument("--budget-s", type=float, default=120.0)
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory (database)")
    ap.add_argument("--param", action="append", default=[], help="procedure parameter (to try shorter variants)")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="campaign-"))
    url = args.db or f"sqlite:///{tmp / 'campaign.sqlite'}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    py = [sys.executable, "-m", "bench.cli"]
    sim_proc = None
    run_args = py + ["run", "eight_position", "--gyro", "CAMPAIGN", "--json", "--no-progress", "--db", url]
    for p in args.param:
        run_args += ["--param", p]
    if args.mode == "process":
        endpoints = tmp / "endpoints.json"
        sim_proc = subprocess.Popen(py + ["sim", "up", "--speed", str(args.speed), "--endpoints-json", str(endpoints)],
                                    env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        info = _wait_file(endpoints, sim_proc)
        run_args += ["--sim-endpoints", str(endpoints)]
        rate = info["gyro_data_rate_hz"]
    else:
        from bench.sim.bench import default_data_rate

        run_args += ["--sim", "--speed", str(args.speed)]
        rate = default_data_rate(args.speed)
    try:
        t0 = time.monotonic()
        done = subprocess.run(run_args, env=env, capture_output=True, text=True)
        wall = time.monotonic() - t0
    finally:
        if sim_proc is not None:
            sim_proc.terminate()
            sim_proc.wait(20)
    if done.returncode not in (0, 1) or not done.stdout.strip():
        print(done.stderr[-3000:], file=sys.stderr)
        return 1
    doc = json.loads(done.stdout.strip().splitlines()[-1])

    from sqlalchemy import func, select

    from bench.storage.db import open_database
    from bench.storage.models import FrameChunk, Gap

    db = open_database(url)
    with db.session() as s:
        rid = doc["run_id"]
        t_first, t_last = s.execute(select(func.min(FrameChunk.t_first), func.max(FrameChunk.t_last))
                                    .where(FrameChunk.run_id == rid)).one()
        seq_gaps = s.scalar(select(func.count()).select_from(Gap).where(Gap.run_id == rid,
                                                                         Gap.reason.like("sequence%"))) or 0
        missing = s.scalar(select(func.coalesce(func.sum(Gap.frames_missing), 0)).where(Gap.run_id == rid)) or 0
    size_mb = db.size_bytes() / 1e6 if db.dialect == "sqlite" else float("nan")
    db.dispose()
    bench_h = (t_last - t_first) / 3600.0 if t_first is not None else 0.0
    expected = (t_last - t_first) * rate + 1 if t_first is not None else 0
    print(f"mode {args.mode}, speed x{args.speed:g}, gyro data rate {rate:g} Hz, database {url.split(':')[0]}")
    print(f"run {rid}: status {doc['status']} ({doc['outcome']}), steps {doc['step']}/{doc['n_steps']}")
    print(f"wall time {wall:.1f} s for {bench_h:.2f} h of bench time (x{bench_h * 3600 / wall:.0f} effective)")
    print(f"frames stored {doc['frames']} (expected at {rate:g} Hz: {expected:.0f}); gaps {len(doc['gaps'])} "
          f"({seq_gaps} sequence gaps, {missing} frames missing); suspensions {len(doc['suspensions'])}; "
          f"segments {doc['segments']}; database {size_mb:.1f} MB")
    fit = next(iter(doc["fits"].values()), {})
    print(f"fit: {fit.get('status')} {fit.get('fitted') or fit.get('error', '')}")
    if args.keep:
        print(f"kept {tmp}")
    ok = doc["status"] == "completed" and doc["outcome"] == "completed" and missing == 0 and wall <= args.budget_s
    if not ok:
        print("FAILED: " + ", ".join(w for w, bad in (("not completed", doc["outcome"] != "completed"),
                                                       ("frames missing", missing != 0),
                                                       (f"over the {args.budget_s:g} s budget", wall > args.budget_s))
                                     if bad))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

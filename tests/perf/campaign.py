"""Benchmark: the full default ``eight_position`` campaign (S000 3.2, about 46-58 h of bench time) on the
simulated bench in lockstep bench time, at the real sampling rates, timed on the wall.

``python -m tests.perf.campaign [--speed max|N] [--seed 1] [--db URL] [--keep] [--budget-s 120]``

``bench run eight_position --sim --speed max`` (the simulated bench in the run's process on a
``LockstepClock``: probes every 2 s, chamber / table / PSU every 5 s, gyro frames at 1 Hz, all in
bench seconds).  Database: a fresh SQLite file unless ``--db``.  Prints the wall time of the run (start
of ``bench run`` to its end), the bench hours covered, frames stored and expected, gaps and suspensions,
the run's sampling summary (``bench runs show --json``: readings and median / max interval per
device), and exits 1 when the run did not complete, lost frames, sampled a device late (probes over
2 s, chamber over 5 s, table / PSU over 10 s) or took longer than ``--budget-s``.
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
LIMITS_S = {"probes": 2.0, "chamber": 5.0, "turntable": 10.0, "psu": 10.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", default="max")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--db", default=None)
    ap.add_argument("--budget-s", type=float, default=120.0)
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory (database)")
    ap.add_argument("--param", action="append", default=[], help="procedure parameter (to try shorter variants)")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="campaign-"))
    url = args.db or f"sqlite:///{tmp / 'campaign.sqlite'}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    py = [sys.executable, "-m", "bench.cli"]
    run_args = py + ["run", "eight_position", "--gyro", "CAMPAIGN", "--json", "--no-progress", "--db", url,
                     "--sim", "--speed", str(args.speed), "--seed", str(args.seed)]
    for p in args.param:
        run_args += ["--param", p]
    t0 = time.monotonic()
    done = subprocess.run(run_args, env=env, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if done.returncode not in (0, 1) or not done.stdout.strip():
        print(done.stderr[-3000:], file=sys.stderr)
        return 1
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    rid = doc["run_id"]
    show = json.loads(subprocess.run(py + ["runs", "show", str(rid), "--json", "--db", url], env=env,
                                     capture_output=True, text=True, check=True).stdout)
    sampling = show["sampling"]
    gyro = sampling["gyro"]
    rate = 1.0 / gyro["median_interval_s"] if gyro["median_interval_s"] else float("nan")

    from sqlalchemy import func, select

    from bench.storage.db import open_database
    from bench.storage.models import FrameChunk, Gap

    db = open_database(url)
    with db.session() as s:
        t_first, t_last = s.execute(select(func.min(FrameChunk.t_first), func.max(FrameChunk.t_last))
                                    .where(FrameChunk.run_id == rid)).one()
        missing = s.scalar(select(func.coalesce(func.sum(Gap.frames_missing), 0)).where(Gap.run_id == rid)) or 0
    size_mb = db.size_bytes() / 1e6 if db.dialect == "sqlite" else float("nan")
    db.dispose()
    bench_h = (t_last - t_first) / 3600.0 if t_first is not None else 0.0
    expected = (t_last - t_first) * rate + 1 if t_first is not None else 0
    print(f"lockstep bench, --speed {args.speed}, seed {args.seed}, gyro {rate:g} Hz, database {url.split(':')[0]}")
    print(f"run {rid}: status {doc['status']} ({doc['outcome']}), steps {doc['step']}/{doc['n_steps']}")
    print(f"wall time {wall:.1f} s for {bench_h:.2f} h of bench time (x{bench_h * 3600 / wall:.0f} effective)")
    print(f"frames stored {doc['frames']} (expected at {rate:g} Hz: {expected:.0f}); gaps {len(doc['gaps'])} "
          f"({missing} frames missing); suspensions {len(doc['suspensions'])}; segments {doc['segments']}; "
          f"database {size_mb:.1f} MB")
    print("sampling (bench seconds):")
    late = []
    for device in ("probes", "chamber", "turntable", "psu", "gyro"):
        d = sampling[device]
        print(f"  {device:9s} {d['readings']:8d} readings, median {d['median_interval_s']} s, max {d['max_interval_s']} s")
        if device in LIMITS_S and (d["max_interval_s"] is None or d["max_interval_s"] > LIMITS_S[device]):
            late.append(device)
    fit = next(iter(doc["fits"].values()), {})
    print(f"fit: {fit.get('status')} {fit.get('fitted') or fit.get('error', '')}")
    if args.keep:
        print(f"kept {tmp}")
    ok = (doc["status"] == "completed" and doc["outcome"] == "completed" and missing == 0 and not late
          and wall <= args.budget_s)
    if not ok:
        print("FAILED: " + ", ".join(w for w, bad in (("not completed", doc["outcome"] != "completed"),
                                                       ("frames missing", missing != 0),
                                                       (f"late: {', '.join(late)}", bool(late)),
                                                       (f"over the {args.budget_s:g} s budget", wall > args.budget_s))
                                     if bad))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

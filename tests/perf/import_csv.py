"""Benchmark: ``bench import`` of a 1,000,000-row measured-data CSV (streamed, all or nothing).

    python -m tests.perf.import_csv [--rows N] [--db URL]

Writes the CSV (time_s, gyro_x/y/z, temp_t1, temp_t2, chamber_pv, orientation: about 100 MB at 1e6
rows), then imports it in a child process into a fresh SQLite file (or ``--db``) and prints the rows
per second of the whole import (check pass + store pass) and the child's peak resident memory.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHUNK = 100_000


def write_big_csv(path: Path, n: int) -> int:
    rng = np.random.default_rng(0)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# gyro_id: PERF-1\n# gyro_type: RLG\n# latitude_deg: 45.75\n# sample_period_s: 0.01\n")
        fh.write("time_s,gyro_x,gyro_y,gyro_z,temp_t1,temp_t2,chamber_pv,orientation\n")
        for start in range(0, n, CHUNK):
            k = min(CHUNK, n - start)
            t = (start + np.arange(k)) * 0.01
            temp = 25.0 + 20.0 * np.sin(t / 3000.0)
            cols = [t, 3.0 + rng.normal(0, 0.5, k), -2.0 + rng.normal(0, 0.5, k), 10.3 + rng.normal(0, 0.5, k),
                    np.round(temp / 0.0625) * 0.0625, np.round((temp - 0.3) / 0.0625) * 0.0625, temp + 1.0]
            text = np.column_stack(cols)
            lines = [",".join(repr(float(v)) for v in row) + ",NUE" for row in text]
            fh.write("\n".join(lines) + "\n")
    return path.stat().st_size


def child(path: str, url: str) -> None:
    from bench.commands.importing import import_csv
    from bench.storage import open_database

    db = open_database(url)
    t0 = time.perf_counter()
    rid = import_csv(db, path, "PERF-1")
    dt = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"RESULT run={rid} seconds={dt:.2f} peak_mb={peak_mb:.0f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--db", default=None, help="database URL (default: a fresh SQLite file)")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        size = write_big_csv(path, args.rows)
        url = args.db or f"sqlite:///{Path(tmp) / 'import.sqlite'}"
        out = subprocess.run([sys.executable, "-m", "tests.perf.import_csv", "--child", str(path), url],
                             capture_output=True, text=True, env=os.environ.copy())
        if out.returncode != 0:
            sys.stderr.write(out.stderr)
            raise SystemExit(out.returncode)
        line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")][-1]
        fields = dict(kv.split("=") for kv in line.split()[1:])
        seconds, peak = float(fields["seconds"]), float(fields["peak_mb"])
        print(f"import of {args.rows:,} rows ({size / 1e6:.0f} MB CSV): {seconds:.1f} s = "
              f"{args.rows / seconds:,.0f} rows/s, peak memory {peak:.0f} MB (target <= 300 MB)")


if __name__ == "__main__":
    main()

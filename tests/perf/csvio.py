"""Benchmark: read and write a day of 1-s measured-data CSV (86,400 rows).

    python -m tests.perf.csvio
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.fit.base import Dataset
from bench.fit.csvio import read_csv, write_csv


def main() -> None:
    n = 86400
    rng = np.random.default_rng(0)
    ds = Dataset({"time_s": np.arange(n, dtype=float), **{f"gyro_{c}": rng.normal(size=n) for c in "xyz"},
                  **{f"temp_t{i}": np.round(rng.normal(25, 5, n) / 0.0625) * 0.0625 for i in range(1, 5)},
                  "chamber_pv": rng.normal(25, 5, n), "orientation": np.full(n, "NUE", dtype=object)},
                 {"gyro_id": "perf"})
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "day.csv"
        t0 = time.perf_counter()
        write_csv(ds, path)
        t1 = time.perf_counter()
        back = read_csv(path)
        t2 = time.perf_counter()
    assert len(back) == n
    print(f"a day of 1-s data ({n} rows, {len(ds.columns)} columns): write {t1 - t0:.2f} s, read {t2 - t1:.2f} s "
          f"(target < 1 s)")


if __name__ == "__main__":
    main()

"""Benchmark: the S001 37-term model by least squares on 10^6 samples (target <= 2 s).

Run: ``python -m tests.perf.fit37``.  Prints the time of the least-squares solve on the 37-column
design (``bench.fit.linear.lstsq``), and of the whole ``fit_model("patent37", ...)`` pipeline
(dT/dt filters, design, Pauta refit, validity hull) for information.  Synthetic data: four probes
lagging a chamber ramp program (first-order lags via scipy.signal.lfilter), bias from a few of the
37 terms plus white noise.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from scipy.signal import lfilter

from bench.fit import models
from bench.fit.base import Dataset
from bench.fit.formula import compile_terms
from bench.fit.linear import lstsq

N = 1_000_000
TARGET_S = 2.0


def synthetic(n: int = N, seed: int = 0) -> Dataset:
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=np.float64) * 0.5                       # 2 Hz, ~139 h
    air = 20.0 + 35.0 * np.sin(2 * np.pi * t / 30000.0) * np.sin(2 * np.pi * t / 7100.0 + 0.3)
    cols = {"time_s": t}
    for name, tau in (("t1", 600.0), ("t2", 900.0), ("t3", 1200.0), ("t4", 300.0)):
        a = np.exp(-0.5 / tau)
        temp = lfilter([1 - a], [1, -a], air, zi=[a * air[0]])[0]
        cols[f"temp_{name}"] = np.round(temp / 0.0625) * 0.0625
    d1 = cols["temp_t1"] - 25.0
    cols["gyro_x"] = 0.1 + 0.01 * d1 + 2e-4 * d1 ** 2 + 0.05 * (cols["temp_t2"] - cols["temp_t3"]) \
        + rng.normal(0, 0.05, n)
    return Dataset(cols, {"gyro_id": "perf37"})


def main() -> int:
    ds = synthetic()
    from bench.fit.prep import add_rates
    work = add_rates(ds)
    terms = []
    for p in ("t1", "t2", "t3", "t4"):
        c, r = f"({p}-25.0)", f"d{p}"
        for expr in (c, f"{c}^2", f"{c}^3", r, f"{r}^2", f"{r}^3", f"{c}*{r}", f"({c}*{r})^2", f"({c}*{r})^3"):
            terms.append((f"a{len(terms) + 1}", expr))
    compiled = compile_terms(terms, work.columns, intercept="a0")
    t0 = time.perf_counter()
    x, _ = compiled.design(work)
    t_design = time.perf_counter() - t0
    y = np.asarray(work["gyro_x"])
    t0 = time.perf_counter()
    fit = lstsq(x, y, names=compiled.names)
    t_ls = time.perf_counter() - t0
    print(f"37-term least squares on {N} samples: {t_ls:.3f} s (target <= {TARGET_S:.1f} s); "
          f"design build {t_design:.3f} s; cond {fit.cond:.3g}; rank {fit.rank}; rms {fit.rms:.4f} deg/h")
    t0 = time.perf_counter()
    res = models.fit_model("patent37", ds, "x")
    t_all = time.perf_counter() - t0
    print(f"full fit_model('patent37') pipeline: {t_all:.3f} s (rates, design, Pauta refit, hull); "
          f"rms {res.stats['rms_dph']:.4f} deg/h, rejected {res.stats['n_rejected']}")
    return 0 if t_ls <= TARGET_S else 1


if __name__ == "__main__":
    sys.exit(main())

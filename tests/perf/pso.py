"""Benchmark: PSO with the paper's settings (seed 002: 200 particles x 200 iterations, c1 = c2 = 1.5,
w = 0.8) on the eq-7 HRG bias model, against least squares.

Run: .venv/bin/python -m tests.perf.pso [n_samples]
Prints wall time of LS, of one PSO run (cost through the QR-compressed form) and of a PSO run with
the cost evaluated directly on all samples, plus the costs.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from bench.fit import pso
from bench.fit.hrg import Eq7Problem, eq7_design, fit_eq7_ls, fit_eq7_pso


def synthetic(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 12 * 3600.0, n)
    T = np.interp(t, [0, 7200, 10800, 16200, 43200], [25, -35, -35, 55, 55])
    rate = np.gradient(T, t / 60.0)
    y = eq7_design(T, rate) @ np.array([0.3, 0.02, -1.5e-4, -0.8, 0.6, 0.01]) + rng.normal(0, 0.3, n)
    return T, rate, y


def main(n: int = 100_000) -> None:
    T, rate, y = synthetic(n)
    t0 = time.perf_counter()
    _, ls = fit_eq7_ls(T, rate, y)
    t_ls = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, seeded = fit_eq7_pso(T, rate, y, seed_with_ls=True)
    t_seeded = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, unseeded = fit_eq7_pso(T, rate, y, seed_with_ls=False)
    t_unseeded = time.perf_counter() - t0

    prob = Eq7Problem(T, rate, y)
    X = eq7_design((T - prob.tc) / prob.ts, (rate - prob.rc) / prob.rs)
    yn = (y - prob.ym) / prob.ys
    direct_n = min(n, 20_000)
    Xd, yd = X[:direct_n], yn[:direct_n]
    t0 = time.perf_counter()
    pso.minimize(lambda th: ((yd[:, None] - Xd @ th.T) ** 2).sum(axis=0), -3 * np.ones(6), 3 * np.ones(6))
    t_direct = time.perf_counter() - t0

    print(f"samples: {n}")
    print(f"least squares:            {t_ls * 1e3:8.1f} ms   cost {ls['cost']:.6g}")
    print(f"PSO seeded with LS:       {t_seeded * 1e3:8.1f} ms   cost {seeded['cost_pso']:.6g}  "
          f"ratio {seeded['cost_ratio']:.6f}")
    print(f"PSO unseeded:             {t_unseeded * 1e3:8.1f} ms   cost {unseeded['cost_pso']:.6g}  "
          f"ratio {unseeded['cost_ratio']:.6f}")
    print(f"PSO direct cost ({direct_n} samples, no QR compression): {t_direct * 1e3:8.1f} ms")
    print(f"condition number: raw design {ls['cond_raw']:.3g}, standardised {ls['cond_std']:.3g}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)

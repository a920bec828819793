"""Least-squares engine and HAC / decimation helpers."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from bench.fit import linear


def test_lstsq_matches_numpy_and_skips_bad_rows():
    rng = np.random.default_rng(0)
    x = np.column_stack([np.ones(5000), rng.normal(size=(5000, 4))])
    beta = np.array([1.0, -2.0, 0.5, 3.0, 1e-3])
    y = x @ beta + rng.normal(0, 0.1, 5000)
    y[10] = np.nan
    x[20, 2] = np.inf
    fit = linear.lstsq(x, y, names=list("abcde"))
    ok = np.isfinite(y) & np.all(np.isfinite(x), axis=1)
    ref = np.linalg.lstsq(x[ok], y[ok], rcond=None)[0]
    np.testing.assert_allclose(fit.coef, ref, rtol=1e-9, atol=1e-12)
    assert fit.n == 4998 and np.isnan(fit.residual[[10, 20]]).all()
    assert fit.as_dict()["d"] == pytest.approx(ref[3])
    assert fit.rms == pytest.approx(0.1, rel=0.05) and 0.99 < fit.r2 <= 1


def test_weighted_equals_repeated_rows():
    rng = np.random.default_rng(1)
    x = np.column_stack([np.ones(300), rng.normal(size=300)])
    y = 2 + 3 * x[:, 1] + rng.normal(size=300)
    w = rng.integers(1, 4, 300).astype(float)
    fit = linear.lstsq(x, y, weights=w)
    rep = np.repeat(np.arange(300), w.astype(int))
    ref = np.linalg.lstsq(x[rep], y[rep], rcond=None)[0]
    np.testing.assert_allclose(fit.coef, ref, rtol=1e-10)


def test_ill_conditioned_design_goes_through_qr_and_stays_accurate():
    rng = np.random.default_rng(2)
    temp = np.linspace(233.0, 333.0, 100_000)            # kelvin: raw powers are badly conditioned
    x = np.vander(temp, 6, increasing=True)
    beta = np.array([1, 2e-2, -3e-4, 1e-6, 2e-9, 1e-12])
    y = x @ beta + rng.normal(0, 1e-6, temp.size)
    fit = linear.lstsq(x, y)
    assert fit.cond > linear._SEMI_NORMAL_MAX_COND     # QR path
    assert fit.rms == pytest.approx(1e-6, rel=0.05)    # reaches the noise: no precision loss
    # a duplicated column is rank deficient: reported, not a crash
    fit2 = linear.lstsq(np.column_stack([x[:, :3], x[:, 2]]), y)
    assert fit2.rank == 3


def test_hac_wald_is_less_fooled_by_autocorrelation_than_plain_ols():
    rng = np.random.default_rng(3)
    n = 4000
    e = np.zeros(n)
    for i in range(1, n):                         # strongly autocorrelated residual (AR(1), phi 0.98)
        e[i] = 0.98 * e[i - 1] + rng.normal()
    z = np.cumsum(rng.normal(size=n))             # an unrelated slowly varying candidate regressor
    x = np.column_stack([np.ones(n), z])
    _stat, p_hac, df = linear.wald_hac(x, e, [1])
    import statsmodels.api as sm
    p_ols = sm.OLS(e, x).fit().pvalues[1]
    assert df == 1 and p_hac > p_ols
    assert linear.newey_west_lags(4000) == int(np.floor(4 * (40) ** (2 / 9)))


def test_decimate_indices_one_per_window():
    t = np.arange(0.0, 1000.0, 0.5)
    idx = linear.decimate_indices(t, 100.0)
    assert len(idx) == 10 and np.all(np.diff(t[idx]) == 100.0)
    assert linear.bic(1.0, 100, 3) == pytest.approx(100 * np.log(0.01) + 3 * np.log(100))


def test_blas_thread_limit_holds_inside_nests_and_restores_the_library_count():
    # in a fresh process whose BLAS starts with two threads (the suite's own processes start with one)
    code = """
from threadpoolctl import threadpool_info
from bench.signal.lstsq import blas_threads
count = lambda: sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
seen = [count()]
with blas_threads():
    seen.append(count())
    with blas_threads():
        seen.append(count())
    seen.append(count())
seen.append(count())
print(seen)
"""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[[2], [1], [1], [1], [2]]", out.stdout

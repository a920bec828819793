"""Least-squares engine and helpers for autocorrelated residuals (the solver, the Newey-West lag count
and the HAC Wald test are defined in ``bench.signal``; this module re-exports them for the models).

* ``lstsq``: ordinary (optionally weighted) least squares for large designs (10^6 x 40).  Columns are
  equilibrated (divided by their 2-norm; calibration-notes lesson 2/10: ill-conditioning, not the
  optimiser, is the usual problem) and the 2-norm condition number of the equilibrated design is
  reported as ``cond``.  When cond <= 1e6 the fast path solves the equilibrated normal equations by
  eigen-decomposition and applies one step of iterative refinement on the residual (corrected
  semi-normal equations; one BLAS pass per step, ~10 significant digits left).  Worse-conditioned
  designs go through a chunked Householder QR of [X/s, y] (TSQR: R factors of row blocks stacked and
  reduced again) and an SVD of R with relative cut-off ``rcond`` (rank reported).  BLAS runs with
  ``BLAS_THREADS`` (default 1, via threadpoolctl) threads during the solve.  Rows with any
  non-finite value in X or y are left out and get a NaN residual.
* HAC / decimation helpers (calibration-notes 4.1 and lesson 3: thermal-run residuals are strongly
  autocorrelated, plain F-tests mislead): ``newey_west_lags`` (floor(4 (n/100)^(2/9)), statsmodels'
  default), ``ols_hac`` (statsmodels OLS with ``cov_type="HAC"``), ``wald_hac`` (robust joint test that
  some coefficients are zero), ``decimate_indices`` (one sample per ``every_s`` seconds) and
  ``bic``.

Public API::

    lstsq(x, y, *, names=None, weights=None, rcond=1e-12, chunk_rows=131072) -> LinearFit
    bic(rss, n, k) -> float
    newey_west_lags(n) -> int
    ols_hac(x, y, maxlags=None) -> statsmodels RegressionResults
    wald_hac(x, y, columns, maxlags=None) -> (statistic, p_value, df)
    decimate_indices(time_s, every_s) -> int array
"""
from __future__ import annotations

import numpy as np

from bench.signal.lstsq import (  # noqa: F401  (the one least-squares solver; re-exported)
    _SEMI_NORMAL_MAX_COND,
    LinearFit,
    bic,
    lstsq,
)
from bench.signal.stats import newey_west_lags, ols_hac  # noqa: F401  (re-exported)
from bench.signal.stats import hac_wald_test


def wald_hac(x: np.ndarray, y: np.ndarray, columns: list[int], maxlags: int | None = None) -> tuple[float, float, int]:
    """Robust (HAC) Wald test that the coefficients of ``columns`` are all zero: (chi2, p, df)
    (``bench.signal.hac_wald_test``)."""
    test = hac_wald_test(x, y, columns, maxlags)
    return test.statistic, test.p_value, test.df


def decimate_indices(time_s: np.ndarray, every_s: float) -> np.ndarray:
    """Indices of the first sample in each consecutive ``every_s`` window (one point per window)."""
    t = np.asarray(time_s, dtype=np.float64)
    if len(t) == 0:
        return np.array([], dtype=np.int64)
    block = np.floor((t - t[0]) / float(every_s)).astype(np.int64)
    first = np.r_[True, block[1:] != block[:-1]]
    return np.flatnonzero(first)

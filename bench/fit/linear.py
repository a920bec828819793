"""Least squares for the linear models: ``bench.signal.lstsq`` (column-equilibrated solver, see there),
re-exported with ``LinearFit``, ``bic`` and ``newey_west_lags``, plus two helpers for autocorrelated
residuals (calibration-notes 4.1 and lesson 3: thermal-run residuals are strongly autocorrelated,
plain F-tests mislead).

Public API::

    lstsq(x, y, *, names=None, weights=None, rcond=1e-12, chunk_rows=131072) -> LinearFit
    bic(rss, n, k) -> float
    newey_west_lags(n) -> int
    wald_hac(x, y, columns, maxlags=None) -> (chi2 statistic, p_value, df)   (bench.signal.hac_wald_test)
    decimate_indices(time_s, every_s) -> int array (first sample of each ``every_s`` window)
"""
from __future__ import annotations

import numpy as np

from bench.signal.lstsq import (  # noqa: F401  (the one least-squares solver; re-exported)
    _SEMI_NORMAL_MAX_COND,
    LinearFit,
    bic,
    lstsq,
)
from bench.signal.stats import hac_wald_test, newey_west_lags  # noqa: F401  (newey_west_lags re-exported)


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

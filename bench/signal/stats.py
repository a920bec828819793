"""Residual statistics for autocorrelated data: lag-1 autocorrelation, Newey-West lag count, the HAC
Wald test (calibration-notes 4.1 and lesson 3: thermal-run residuals are strongly autocorrelated and
plain F-tests mislead).

The HAC Wald test uses the chi-squared reference distribution: with a Newey-West covariance the Wald
statistic is only asymptotically distributed, as chi2(q); an F(q, n - k) reference would claim a
small-sample exactness that the HAC estimator does not have (it is also statsmodels' default for a
HAC fit without ``use_t``, which is what both earlier copies used).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


def lag1_autocorrelation(x: np.ndarray, segments: list[slice] | None = None) -> float:
    """Lag-1 autocorrelation sum(r_i r_{i+1}) / sum(r_i^2) of ``x`` (unitless), r = x minus its mean per
    segment; pairs never cross a segment boundary; non-finite samples are dropped (the rest of the
    segment joined).  0.0 when there is no variance."""
    v = np.asarray(x, dtype=np.float64)
    if segments is None:
        segments = [slice(0, v.size)]
    num = den = 0.0
    for seg in segments:
        r = v[seg]
        r = r[np.isfinite(r)]
        if r.size < 2:
            continue
        r = r - r.mean()
        num += float(np.dot(r[:-1], r[1:]))
        den += float(np.dot(r, r))
    return num / den if den > 0 else 0.0


def newey_west_lags(n: int) -> int:
    """Newey-West HAC lag count floor(4 (n/100)^(2/9)) for ``n`` samples (statsmodels' default), at least 1."""
    return max(1, int(np.floor(4.0 * (n / 100.0) ** (2.0 / 9.0))))


def finite_rows(x: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask of rows where every column of ``x`` (and ``y``) is finite."""
    x = np.asarray(x)
    ok = np.all(np.isfinite(x), axis=1) if x.ndim == 2 else np.isfinite(x)
    return ok & np.isfinite(y) if y is not None else ok


def column_scale(x: np.ndarray) -> np.ndarray:
    """RMS of each column (1 for an all-zero column): dividing by it equilibrates a design."""
    scale = np.sqrt(np.mean(np.asarray(x, dtype=np.float64) ** 2, axis=0))
    scale[scale == 0] = 1.0
    return scale


def ols_hac(x: np.ndarray, y: np.ndarray, maxlags: int | None = None):
    """statsmodels OLS of y on the columns of ``x`` with Newey-West (HAC) covariance; rows with a
    non-finite value are dropped; ``maxlags`` defaults to ``newey_west_lags(n)``."""
    import statsmodels.api as sm

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = finite_rows(x, y)
    lags = newey_west_lags(int(ok.sum())) if maxlags is None else int(maxlags)
    return sm.OLS(y[ok], x[ok]).fit(cov_type="HAC", cov_kwds={"maxlags": lags})


class WaldTest(NamedTuple):
    statistic: float
    p_value: float
    df: int
    distribution: str           # reference distribution of the statistic: "chi2"


def hac_wald_test(x: np.ndarray, y: np.ndarray, columns: list[int], maxlags: int | None = None) -> WaldTest:
    """Joint Wald test, with HAC (Newey-West) covariance, that the coefficients of ``columns`` of ``x``
    are all zero; chi2 reference (see the module docstring).  Rows with a non-finite value are dropped;
    columns are scaled (the statistic does not depend on scaling, its rounding does).  Raises
    ``numpy.linalg.LinAlgError`` / ``ValueError`` when the covariance is singular."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = finite_rows(x, y)
    res = ols_hac(x[ok] / column_scale(x[ok]), y[ok], maxlags)
    r = np.zeros((len(columns), x.shape[1]))
    for i, c in enumerate(columns):
        r[i, c] = 1.0
    test = res.wald_test(r, scalar=True, use_f=False)
    return WaldTest(float(test.statistic), float(test.pvalue), len(columns), "chi2")

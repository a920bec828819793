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


class HacFit(NamedTuple):
    """Least squares with Newey-West (HAC) covariance: coefficients, their covariance, the residual
    and the lag count used."""

    params: np.ndarray
    cov: np.ndarray
    resid: np.ndarray
    maxlags: int

    @property
    def pvalues(self) -> np.ndarray:
        """Two-sided p-values of each coefficient against 0 (normal reference, as the HAC Wald test's
        chi2)."""
        from scipy.stats import norm

        se = np.sqrt(np.maximum(np.diag(self.cov), 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            return 2.0 * norm.sf(np.abs(self.params / se))


def ols_hac(x: np.ndarray, y: np.ndarray, maxlags: int | None = None) -> HacFit:
    """OLS of y on the columns of ``x`` with Newey-West (HAC) covariance, Bartlett weights, no
    small-sample correction (statsmodels' ``OLS(...).fit(cov_type="HAC")``, written out in numpy: the
    close-the-loop search calls it often and importing statsmodels costs more than the analysis);
    rows with a non-finite value are dropped; ``maxlags`` defaults to ``newey_west_lags(n)``."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = finite_rows(x, y)
    x, y = x[ok], y[ok]
    lags = newey_west_lags(len(y)) if maxlags is None else int(maxlags)
    pinv = np.linalg.pinv(x)
    beta = pinv @ y
    resid = y - x @ beta
    xu = x * resid[:, None]
    s = xu.T @ xu
    for lag in range(1, min(lags, len(y) - 1) + 1):
        g = xu[lag:].T @ xu[:-lag]
        s += (1.0 - lag / (lags + 1.0)) * (g + g.T)
    bread = pinv @ pinv.T                                   # (X'X)^-1
    return HacFit(beta, bread @ s @ bread.T, resid, lags)


def ljung_box(x: np.ndarray, lags: int) -> tuple[float, float]:
    """Ljung-Box statistic of the first ``lags`` autocorrelations of ``x`` (demeaned, non-finite
    samples dropped) and its chi2(lags) p-value (statsmodels' ``acorr_ljungbox``, model_df = 0)."""
    from scipy.stats import chi2

    v = np.asarray(x, dtype=np.float64)
    v = v[np.isfinite(v)]
    v = v - v.mean()
    n = len(v)
    den = float(v @ v)
    if n <= lags or den <= 0:
        raise ValueError(f"ljung_box: {n} samples with variance {den:.3g} cannot test {lags} lags")
    acf = np.array([float(v[k:] @ v[:-k]) / den for k in range(1, lags + 1)])
    q = float(n * (n + 2.0) * np.sum(acf ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(chi2.sf(q, lags))


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
    from scipy.stats import chi2

    res = ols_hac(x[ok] / column_scale(x[ok]), y[ok], maxlags)
    b = res.params[columns]
    v = res.cov[np.ix_(columns, columns)]
    stat = float(b @ np.linalg.pinv(v) @ b)
    if not np.isfinite(stat):
        raise ValueError("hac_wald_test: the robust covariance of the tested coefficients is not finite")
    return WaldTest(stat, float(chi2.sf(stat, len(columns))), len(columns), "chi2")

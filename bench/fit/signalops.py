"""The few signal operations close-the-loop uses (block means, lag-1 autocorrelation, Allan variance,
scaled least squares, HAC Wald test), kept in this one place.  Pure functions over arrays."""
from __future__ import annotations

import warnings

import numpy as np

from bench.fit.linear import newey_west_lags
from bench.fit.metrics import bias_stability


def sample_period(time_s: np.ndarray) -> float:
    if len(time_s) < 2:
        return 1.0
    return float(np.median(np.diff(time_s)))


def block_means(x: np.ndarray, time_s: np.ndarray, block_s: float) -> np.ndarray:
    """Means over consecutive blocks of ``block_s`` seconds (last partial block dropped); x may be
    1-D or 2-D (rows = samples); an all-missing block is NaN."""
    per = max(1, int(round(block_s / sample_period(time_s))))
    n = (len(x) // per) * per
    if n == 0:
        return x[:0]
    shaped = x[:n].reshape((n // per, per) + x.shape[1:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(shaped, axis=1)


def std100(residual: np.ndarray, time_s: np.ndarray) -> float:
    """Bias stability: std of 100-s means (GJB 2426A convention), the fitting module's definition."""
    return bias_stability(time_s, residual, 100.0)


def rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def finite_rows(X: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    ok = np.all(np.isfinite(X), axis=1) if X.ndim == 2 else np.isfinite(X)
    return ok & np.isfinite(y) if y is not None else ok


def lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares on column-scaled X (numerically safe for powers of temperature); rows with a
    missing value are left out."""
    ok = finite_rows(X, y)
    X, y = X[ok], y[ok]
    scale = np.sqrt(np.mean(X ** 2, axis=0)) if len(X) else np.ones(X.shape[1])
    scale[~(scale > 0)] = 1.0
    beta, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    return beta / scale


def lag1(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if len(x) < 3:
        return 0.0
    x = x - x.mean()
    den = float(np.dot(x, x))
    return float(np.dot(x[1:], x[:-1]) / den) if den > 0 else 0.0


def hac_wald_p(X: np.ndarray, y: np.ndarray, new_cols: list[int]) -> float:
    """p-value of the joint Wald test that the ``new_cols`` coefficients are 0, HAC (Newey-West)
    covariance."""
    import statsmodels.api as sm

    ok = finite_rows(X, y)
    X, y = X[ok], y[ok]
    maxlags = max(1, newey_west_lags(len(y)))
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    scale[~(scale > 0)] = 1.0
    try:
        res = sm.OLS(y, X / scale).fit(cov_type="HAC", cov_kwds={"maxlags": maxlags})
        R = np.zeros((len(new_cols), X.shape[1]))
        for i, c in enumerate(new_cols):
            R[i, c] = 1.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return float(res.wald_test(R, scalar=True).pvalue)
    except (np.linalg.LinAlgError, ValueError):
        return 1.0


def allan_variance(y: np.ndarray, dt: float, tau_max_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance of a rate series y (sample period dt) at taus dt * 2^k <= tau_max_s.
    Returns (taus, variances, number of terms)."""
    y = np.asarray(y, dtype=np.float64)
    y = y - np.mean(y)
    x = np.concatenate([[0.0], np.cumsum(y)]) * dt        # phase (integrated rate)
    n = len(x)
    taus, avar, terms = [], [], []
    m = 1
    while m * dt <= tau_max_s and n - 2 * m >= 2:
        d = x[2 * m:] - 2.0 * x[m:-m] + x[:-2 * m]
        tau = m * dt
        taus.append(tau)
        avar.append(float(np.mean(d ** 2) / (2.0 * tau ** 2)))
        terms.append(len(d))
        m *= 2
    return np.array(taus), np.array(avar), np.array(terms)

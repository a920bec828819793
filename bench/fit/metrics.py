"""Performance metrics of a gyro bias (raw or residual after compensation).

Definitions and sources:

* Bias stability (零偏稳定性, S001 B_s; S000 Table 3 "百秒标准差"): standard deviation (ddof = 1) of
  the means over consecutive ``window_s`` = 100 s windows.  ``bias_stability_3sigma`` = 3 x that,
  the "(deg/h)(3 sigma)" form quoted in S002 Table 4.
* Bias repeatability (零偏重复性, S001 B_r): standard deviation (ddof = 1) of the per-run biases.
* Allan deviation: ``bench.signal.allan_deviation`` (allantools ``oadev``, data_type "freq", octave
  taus; non-finite samples dropped; at least ``bench.signal.MIN_ALLAN_SAMPLES`` samples).  IEEE 952 readings:
  ARW N = sigma(tau = 1 s) [deg/h] / 60 -> deg/sqrt(h) (log-log interpolation; when 1 s is below the
  shortest tau, extrapolated on the -1/2 slope from the shortest tau); bias instability
  B = min sigma / 0.664 (deg/h); rate random walk K from a +1/2-slope line fitted to the taus after the
  minimum whose local slope exceeds +1/4, read at tau = 3 s (sigma = K sqrt(tau/3)), reported in
  deg/h/sqrt(h) (= 60 x the value in deg/h/sqrt(s)); None when there is no rising part.
* Improvement %: 100 (before - after) / before.
* Profile correlation r (S001 weak-correlation rule r < 0.4): the two chamber temperature series are
  put on **elapsed time since each run's first sample**, truncated to the shorter run, linearly
  resampled on a common grid with step = the larger of the two median sample periods (or ``step_s``),
  samples where either is NaN dropped, then Pearson r = Cov(X, Y) / (sigma_X sigma_Y).

Public API::

    window_means(time_s, x, window_s=100.0, min_fraction=0.5) -> array
    window_numbers(time_s, x, window_s=100.0, min_fraction=0.5) -> array
    bias_stability(time_s, x, window_s=100.0) -> float
    bias_stability_3sigma(time_s, x, window_s=100.0) -> float
    bias_repeatability(run_biases) -> float
    allan(x, rate_hz=1.0, taus="octave") -> AllanResult
    improvement_pct(before, after) -> float
    profile_correlation(time_a, temp_a, time_b, temp_b, step_s=None) -> float
    weakly_correlated(r, limit=0.4, absolute=True) -> bool   (|r| < 0.4 by default; see docstring)
    residual_summary(time_s, resid, rate_hz=None) -> dict
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.signal import allan_deviation, block_means

BI_FACTOR = 0.664


def _windows(time_s: np.ndarray, x: np.ndarray, window_s: float, min_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(number, mean) of every window ``window_means`` keeps (see there)."""
    t = np.asarray(time_s, dtype=np.float64)
    v = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return np.array([]), np.array([])
    step = float(np.median(np.diff(t))) if t.size > 1 else float(window_s)
    if step >= 0.9 * window_s:
        return np.round((t[ok] - t[0]) / float(window_s)), v[ok]
    ids = np.floor((t - t[0]) / float(window_s)).astype(np.int64)
    rows = np.bincount(ids)
    n = np.bincount(ids, weights=ok.astype(np.float64), minlength=rows.size)
    total = np.bincount(ids, weights=np.where(ok, v, 0.0), minlength=rows.size)
    keep = (n > 0) & (n >= min_fraction * float(np.median(rows[rows > 0])))
    return np.flatnonzero(keep).astype(np.float64), total[keep] / n[keep]


def window_means(time_s: np.ndarray, x: np.ndarray, window_s: float = 100.0, min_fraction: float = 0.5) -> np.ndarray:
    """Means of the finite values of ``x`` over consecutive windows of ``window_s`` seconds counted from
    the record's first sample (one grid for every quantity of a record, whatever is missing in it); a
    window is kept when at least ``min_fraction`` of the usual number of samples per window (the
    median over the windows that hold samples) are finite.  Samples already ``window_s`` or more
    apart are each their own window."""
    return _windows(time_s, x, window_s, min_fraction)[1]


def window_numbers(time_s: np.ndarray, x: np.ndarray, window_s: float = 100.0, min_fraction: float = 0.5) -> np.ndarray:
    """The number, counted from the record's first sample, of every window ``window_means`` keeps, in
    its order: a stretch left out (out of range, an outage) keeps its length between the windows
    either side."""
    return _windows(time_s, x, window_s, min_fraction)[0]


def bias_stability(time_s: np.ndarray, x: np.ndarray, window_s: float = 100.0) -> float:
    """Std (ddof=1) of ``window_s`` means, 1 sigma, in the unit of ``x``; NaN with < 2 windows."""
    m = window_means(time_s, x, window_s)
    return float(np.std(m, ddof=1)) if len(m) >= 2 else float("nan")


def bias_stability_3sigma(time_s: np.ndarray, x: np.ndarray, window_s: float = 100.0) -> float:
    return 3.0 * bias_stability(time_s, x, window_s)


def bias_repeatability(run_biases) -> float:
    """S001 B_r: std (ddof=1) of per-run biases; NaN with fewer than 2 runs."""
    b = np.asarray(list(run_biases), dtype=np.float64)
    b = b[np.isfinite(b)]
    return float(np.std(b, ddof=1)) if len(b) >= 2 else float("nan")


@dataclass
class AllanResult:
    taus: np.ndarray
    adev: np.ndarray
    n: np.ndarray
    arw_deg_per_rt_h: float
    adev_at_1s_dph: float
    bias_instability_dph: float
    bias_instability_tau_s: float
    rrw_dph_per_rt_h: float | None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        return {"arw_deg_per_rt_h": self.arw_deg_per_rt_h, "adev_at_1s_dph": self.adev_at_1s_dph,
                "bias_instability_dph": self.bias_instability_dph,
                "bias_instability_tau_s": self.bias_instability_tau_s, "rrw_dph_per_rt_h": self.rrw_dph_per_rt_h,
                "adev_min_dph": float(np.min(self.adev)) if len(self.adev) else float("nan")}


def allan(x: np.ndarray, rate_hz: float = 1.0, taus: str | np.ndarray = "octave") -> AllanResult:
    """Overlapping Allan deviation of a rate series (deg/h; ``bench.signal.allan_deviation``) and the
    IEEE 952 readings."""
    t, ad, n, dropped = allan_deviation(x, rate_hz, taus)
    notes = [f"{dropped} non-finite samples dropped (series joined)"] if dropped else []
    lt, la = np.log(t), np.log(ad)
    if t[0] <= 1.0 <= t[-1]:
        s1 = float(np.exp(np.interp(0.0, lt, la)))
    else:
        s1 = float(ad[0] * np.sqrt(t[0] / 1.0))
        notes.append(f"ARW extrapolated on the -1/2 slope from tau = {t[0]:g} s")
    imin = int(np.argmin(ad))
    rrw = None
    if imin < len(t) - 1:
        slopes = np.diff(la) / np.diff(lt)
        rising = [i + 1 for i in range(imin, len(t) - 1) if slopes[i] > 0.25]
        if rising:
            c = float(np.mean(la[rising] - 0.5 * lt[rising]))
            rrw = float(np.exp(c) * np.sqrt(3.0)) * 60.0
    return AllanResult(taus=t, adev=ad, n=n, arw_deg_per_rt_h=s1 / 60.0, adev_at_1s_dph=s1,
                       bias_instability_dph=float(ad[imin] / BI_FACTOR), bias_instability_tau_s=float(t[imin]),
                       rrw_dph_per_rt_h=rrw, notes=notes)


def improvement_pct(before: float, after: float) -> float:
    return float(100.0 * (before - after) / before) if before else float("nan")


def profile_correlation(time_a: np.ndarray, temp_a: np.ndarray, time_b: np.ndarray, temp_b: np.ndarray,
                        step_s: float | None = None) -> float:
    """Pearson r of two runs' chamber profiles aligned on elapsed time (see module docstring)."""
    ta = np.asarray(time_a, float) - float(time_a[0])
    tb = np.asarray(time_b, float) - float(time_b[0])
    xa, xb = np.asarray(temp_a, float), np.asarray(temp_b, float)
    if step_s is None:
        step_s = max(float(np.median(np.diff(ta))), float(np.median(np.diff(tb))))
    end = min(ta[-1], tb[-1])
    grid = np.arange(0.0, end + step_s / 2, step_s)
    fa, fb = np.isfinite(xa), np.isfinite(xb)
    ya = np.interp(grid, ta[fa], xa[fa], left=np.nan, right=np.nan)
    yb = np.interp(grid, tb[fb], xb[fb], left=np.nan, right=np.nan)
    ok = np.isfinite(ya) & np.isfinite(yb)
    if ok.sum() < 3:
        return float("nan")
    ya, yb = ya[ok], yb[ok]
    if np.std(ya) == 0 or np.std(yb) == 0:
        return float("nan")
    return float(np.corrcoef(ya, yb)[0, 1])


def weakly_correlated(r: float, limit: float = 0.4, *, absolute: bool = True) -> bool:
    """S001 rule: the validation run is weakly correlated with the modelling run when r < 0.4.

    The patent writes r < 0.4 with -1 <= r <= 1; read literally a mirrored profile (r = -0.9) would
    pass although it is strongly (anti-)correlated, so by default |r| < limit is used;
    ``absolute=False`` gives the literal rule."""
    if not np.isfinite(r):
        return False
    return bool((abs(r) if absolute else r) < limit)


def residual_summary(time_s: np.ndarray, resid: np.ndarray, rate_hz: float | None = None) -> dict:
    """RMS, peak-to-peak, mean, 100-s stability (1 sigma and 3 sigma) and Allan readings of a residual."""
    r = np.asarray(resid, float)
    f = r[np.isfinite(r)]
    out = {"n": int(f.size), "mean_dph": float(np.mean(f)) if f.size else float("nan"),
           "rms_dph": float(np.sqrt(np.mean(f ** 2))) if f.size else float("nan"),
           "p2p_dph": float(np.ptp(f)) if f.size else float("nan"),
           "std100_dph": bias_stability(time_s, r, 100.0), "std100_3sigma_dph": bias_stability_3sigma(time_s, r, 100.0)}
    if rate_hz is None and len(time_s) > 1:
        rate_hz = 1.0 / float(np.median(np.diff(np.asarray(time_s, float))))
    if f.size >= 64 and rate_hz:
        out.update(allan(f, rate_hz).summary())
    return out

"""Temperature rate dT/dt in C/min, time first: ``temperature_rate(time_s, temp_c, window_s, method=...)``.

Two filters, each named wherever a result uses it (``definition["rate_method"]``):

* ``"centred_slope"`` (default; the linear models' ``rate_window_s`` terms, close-the-loop): the
  centred least-squares slope over ``window_s`` seconds (Savitzky-Golay first derivative, polyorder 1,
  which equals polyorder 2 at the window centre; within half a window of the record's ends, polyorder
  2's slope at the sample), computed on the series linearly resampled to a uniform grid at the median
  sample period; samples whose window is not covered by data (a gap longer than ``window_s/2``) get
  NaN, as do samples outside the measured span.  Calibration-notes lesson 9.
* ``"savgol2"`` (FOG and HRG models, seed 004: the rate "by differencing the 100-s smoothed
  temperature"): Savitzky-Golay order 2 over ``window_s`` per segment when the window spans >= 3
  samples, else central differences (``np.gradient``); never NaN (a segment of one sample gets 0).

``segments`` (see ``bench.signal.segments``) are filtered separately; by default the whole record is
one segment for ``savgol2`` and ``centred_slope`` handles gaps itself.
"""
from __future__ import annotations

import numpy as np

RATE_METHODS = ("centred_slope", "savgol2")
DEFAULT_RATE_METHOD = "centred_slope"


def check_rate_method(method: str) -> str:
    if method not in RATE_METHODS:
        raise ValueError(f"rate method {method!r} unknown (known: {', '.join(RATE_METHODS)})")
    return method


def temperature_rate(time_s: np.ndarray, temp_c: np.ndarray, window_s: float, method: str = DEFAULT_RATE_METHOD,
                     segments: list[slice] | None = None, near_gaps: str = "missing") -> np.ndarray:
    """dT/dt in C/min of ``temp_c`` (C) sampled at ``time_s`` (s), filtered over ``window_s`` (s) with
    ``method`` (one of ``RATE_METHODS``, see the module docstring).  ``near_gaps``: ``"missing"``
    leaves NaN where the window reaches into a gap longer than half of it; ``"present"`` (the centred
    slope of a whole record only) gives there the least-squares slope of the readings present in the
    window (one-sided beside the gap; NaN when fewer than three)."""
    check_rate_method(method)
    if near_gaps not in ("missing", "present"):
        raise ValueError(f"near_gaps must be 'missing' or 'present', got {near_gaps!r}")
    if near_gaps == "present" and (segments is not None or method != "centred_slope"):
        raise ValueError("near_gaps='present' applies to the centred slope of a whole record (no segments)")
    if method == "savgol2":
        return _savgol(time_s, temp_c, window_s, segments)[1]
    if segments is None:
        return CentredSlopeRate(time_s, temp_c).rate(window_s, near_gaps)
    t = np.asarray(time_s, dtype=np.float64)
    out = np.full(t.size, np.nan)
    for seg in segments:
        out[seg] = CentredSlopeRate(t[seg], np.asarray(temp_c, dtype=np.float64)[seg]).rate(window_s)
    return out


def smoothed_temperature(time_s: np.ndarray, temp_c: np.ndarray, window_s: float,
                         segments: list[slice] | None = None) -> np.ndarray:
    """Temperature (C) smoothed by the ``savgol2`` filter (Savitzky-Golay order 2 over ``window_s``)."""
    return _savgol(time_s, temp_c, window_s, segments)[0]


def smoothed_temperature_and_rate(time_s: np.ndarray, temp_c: np.ndarray, window_s: float,
                                  segments: list[slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(``smoothed_temperature``, ``temperature_rate(method="savgol2")``) in one pass: (C, C/min)."""
    return _savgol(time_s, temp_c, window_s, segments)


def _savgol(time_s: np.ndarray, temp_c: np.ndarray, window_s: float,
            segments: list[slice] | None) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(time_s, float)
    x = np.asarray(temp_c, float)
    if segments is None:
        segments = [slice(0, t.size)]
    smooth = x.copy()
    rate = np.zeros_like(x)
    for seg in segments:
        ts, xs = t[seg], x[seg]
        if xs.size < 2:
            continue
        step = float(np.median(np.diff(ts)))
        if step <= 0:
            step = 1.0
        w = int(round(window_s / step)) if window_s > 0 else 1
        w = min(w, xs.size if xs.size % 2 else xs.size - 1)
        if w % 2 == 0:
            w -= 1
        if w >= 3:
            from scipy.signal import savgol_filter   # scipy.signal takes seconds to import: only when used

            smooth[seg] = savgol_filter(xs, w, 2, mode="interp")
            rate[seg] = savgol_filter(xs, w, 2, deriv=1, delta=step / 60.0, mode="interp")
        else:
            rate[seg] = np.gradient(xs, ts / 60.0, edge_order=2 if xs.size >= 3 else 1)
    return smooth, rate


class CentredSlopeRate:
    """The ``centred_slope`` rate (C/min) of one record, at any window: what does not depend on the
    window (the readings on their regular grid, their cumulative sums, the gaps) is done once, so that
    a search over windows pays only for each window's own sums."""

    def __init__(self, time_s: np.ndarray, temp_c: np.ndarray) -> None:
        self.t = t = np.asarray(time_s, dtype=np.float64)
        x = np.asarray(temp_c, dtype=np.float64)
        ok = np.isfinite(x) & np.isfinite(t)
        self.sums: _SlopeSums | None = None
        if ok.sum() < 3:
            return
        self.to, self.xo = to, xo = t[ok], x[ok]
        self.dt = dt = float(np.median(np.diff(to)))
        if dt <= 0:
            raise ValueError("temperature_rate: time must increase")
        self.grid = grid = np.arange(to[0], to[-1] + dt / 2, dt)
        if len(grid) < 3:
            return
        # readings on a regular grid (as most loggers give them) are the grid: no interpolation either way
        self.on_grid = len(to) == len(t) == len(grid) and np.array_equal(grid, to)
        self.sums = _SlopeSums(xo if self.on_grid else np.interp(grid, to, xo))
        self.steps = np.diff(to)
        self.outside = (t < to[0]) | (t > to[-1])

    def rate(self, window_s: float, near_gaps: str = "missing") -> np.ndarray:
        """dT/dt over ``window_s`` (``temperature_rate``'s ``centred_slope`` of the whole record, with its
        ``near_gaps`` rule)."""
        if near_gaps not in ("missing", "present"):
            raise ValueError(f"near_gaps must be 'missing' or 'present', got {near_gaps!r}")
        t = self.t
        out = np.full(len(t), np.nan)
        if self.sums is None:
            return out
        dt, to = self.dt, self.to
        half = max(1, int(round(window_s / dt / 2.0)))
        if len(self.grid) < 2 * half + 1:
            half = max(1, (len(self.grid) - 1) // 2)
        slope = self.sums.slope(half) / dt
        rate = (slope if self.on_grid else np.interp(t, self.grid, slope)) * 60.0
        # samples near a gap longer than half the window: the filter saw interpolated, not measured data
        gaps = np.flatnonzero(self.steps > max(window_s / 2.0, 1.5 * dt))
        for g in gaps:
            lo, hi = to[g], to[g + 1]
            out_mask = (t > lo - window_s / 2.0 + dt) & (t < hi + window_s / 2.0 - dt) & (hi - lo > window_s / 2.0)
            rate[out_mask] = np.nan
        rate[self.outside] = np.nan
        out[:] = rate
        if near_gaps == "present":
            fill = np.isnan(out) & (t >= to[0]) & (t <= to[-1])
            if fill.any():
                out[fill] = _present_slope(to, self.xo, t[fill], window_s)
        return out


def _present_slope(t: np.ndarray, x: np.ndarray, at: np.ndarray, window_s: float) -> np.ndarray:
    """Least-squares slope (C/min) of the readings (t, x) within +-window/2 of each time in ``at``
    (O(n) with cumulative sums); NaN where fewer than three readings lie in the window."""
    lo = np.searchsorted(t, at - window_s / 2.0, side="left")
    hi = np.searchsorted(t, at + window_s / 2.0, side="right")
    tc, xc = t - t[0], x - x.mean()
    c = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(tc), tc, tc * tc, xc, tc * xc)]
    n, st, stt, sx, stx = (ci[hi] - ci[lo] for ci in c)
    den = n * stt - st * st
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (n * stx - st * sx) / den
    return np.where((n >= 3) & (den > 0), slope, np.nan) * 60.0


class _SlopeSums:
    """Least-squares slope (per sample) over x[i-half .. i+half] for any ``half``, O(n) with cumulative
    sums taken once.  Within ``half`` of an end, the derivative of the quadratic fitted to the first /
    last full window, at the sample (= Savitzky-Golay polyorder 2, deriv 1, mode "interp"; at a window's
    centre polyorder 1 and 2 give the same slope): the rate follows the temperature's curvature to the
    record's end instead of holding the last full window's slope for half a window (measured: a relay
    whose 600-s rate froze at -0.16 C/min over the last 300 s of a validation run still cooling at
    -0.26 C/min missed its last switch; its size on that run came out at 0.76x the training size and
    the true effect was turned away, the channel left at 11x the oracle's error)."""

    def __init__(self, x: np.ndarray) -> None:
        n = self.n = len(x)
        self.xc = xc = x - x.mean()             # keep cumulative sums small
        self.j = j = np.arange(n, dtype=np.float64) - n / 2.0
        self.c0 = np.concatenate([[0.0], np.cumsum(xc)])
        self.c1 = np.concatenate([[0.0], np.cumsum(j * xc)])

    def slope(self, half: int) -> np.ndarray:
        n, c0, c1 = self.n, self.c0, self.c1
        w = 2 * half + 1
        # window sums for the centres i = half .. n-half-1: c[i + half + 1] - c[i - half]
        s0 = c0[w:] - c0[:n - w + 1]
        s1 = c1[w:] - c1[:n - w + 1]
        num = s1 - self.j[half:n - half] * s0    # sum over k of k * x[i+k]
        den = half * (half + 1) * w / 3.0        # sum over k of k^2
        out = np.empty(n)
        out[half:n - half] = num / den
        k = np.arange(-half, half + 1, dtype=np.float64)
        q = k * k - k @ k / w                   # the quadratic's column, orthogonal to 1 and k
        for first, at in ((0, slice(0, half)), (n - w, slice(n - half, n))):
            curvature = q @ self.xc[first:first + w] / (q @ q)
            centre = out[first + half]
            out[at] = centre + 2.0 * curvature * (np.arange(at.start, at.stop) - first - half)
        return out

"""First-order linear recurrences with a coefficient per sample: y[i] = a[i] y[i-1] + b[i].

The one definition behind a first-order lag on an irregular time axis (a[i] = exp(-dt[i] / tau)) and
the gradual (Duhem) hysteresis memory (a[i] = exp(-|dT[i]| / width)).  Vectorised: with
L[i] = sum_{j<=i} ln a[j], y[i] = exp(L[i]) (y0 + sum_{j<=i} b[j] exp(-L[j])), evaluated in chunks
over which L falls by at most ``LOG_RANGE`` (so exp(-L) stays finite); within a chunk every term
b[j] exp(L[i] - L[j]) is at most |b[j]|, so the rounding error stays near n * eps * max|b|.
"""
from __future__ import annotations

import numpy as np

LOG_RANGE = 600.0          # exp(600) ~ 4e260 < float64 max
MIN_LOG_A = -50.0          # a below exp(-50) is a full reset either way


def linear_recurrence(a: np.ndarray, b: np.ndarray, y0: float = 0.0) -> np.ndarray:
    """y[i] = a[i] y[i-1] + b[i] with y[-1] = ``y0``; ``a`` in (0, 1] (0 is taken as exp(-50))."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"linear_recurrence: a and b must be 1-D of one length, got {a.shape} and {b.shape}")
    if np.any(a > 1.0) or np.any(~np.isfinite(a)) or np.any(a < 0.0):
        raise ValueError("linear_recurrence: every a[i] must be a finite number in [0, 1]")
    n = len(a)
    out = np.empty(n)
    if n == 0:
        return out
    with np.errstate(divide="ignore"):
        la = np.maximum(np.log(a), MIN_LOG_A)
    L = np.cumsum(la)
    y, start = float(y0), 0
    while start < n:
        base = L[start - 1] if start else 0.0
        end = max(start + 1, int(np.searchsorted(-L, -base + LOG_RANGE, side="right")))
        lc = L[start:end] - base
        out[start:end] = np.exp(lc) * (y + np.cumsum(b[start:end] * np.exp(-lc)))
        y, start = float(out[end - 1]), end
    return out

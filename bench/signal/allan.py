"""Overlapping Allan deviation of a rate series: the one definition.

``allantools.oadev(x, rate=rate_hz, data_type="freq", taus=...)`` (calibration notes 2.1: a gyro rate is
"frequency" data; octave taus by default, never "all" on long series).  One NaN policy: non-finite
samples are dropped and the remaining series joined (their count is returned).  One minimum length:
``MIN_ALLAN_SAMPLES`` finite samples, else ``ValueError`` naming it.  Taus whose deviation is not finite
and positive are left out.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

MIN_ALLAN_SAMPLES = 8


class AllanDeviation(NamedTuple):
    taus_s: np.ndarray          # averaging times (s)
    adev: np.ndarray            # Allan deviation, unit of the input (e.g. deg/h)
    n: np.ndarray               # number of overlapping pairs behind each value
    dropped: int                # non-finite input samples dropped


def allan_deviation(x: np.ndarray, rate_hz: float, taus: str | np.ndarray = "octave") -> AllanDeviation:
    """Overlapping Allan deviation of rate samples ``x`` taken at ``rate_hz`` (Hz); ``taus`` as allantools
    (``"octave"``, ``"decade"``, or an array of seconds)."""
    import allantools

    v = np.asarray(x, dtype=np.float64)
    finite = np.isfinite(v)
    dropped = int(v.size - finite.sum())
    if dropped:
        v = v[finite]
    if v.size < MIN_ALLAN_SAMPLES:
        raise ValueError(f"Allan deviation: need at least {MIN_ALLAN_SAMPLES} finite samples, got {v.size}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"Allan deviation: sample rate must be a positive number of Hz, got {rate_hz!r}")
    t, ad, _err, n = allantools.oadev(v, rate=float(rate_hz), data_type="freq", taus=taus)
    t, ad, n = np.asarray(t, float), np.asarray(ad, float), np.asarray(n)
    good = np.isfinite(ad) & (ad > 0)
    return AllanDeviation(t[good], ad[good], n[good], dropped)

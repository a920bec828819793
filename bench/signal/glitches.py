"""Isolated glitches in a sampled signal: a few samples that leave the signal's local course by far
more than its noise and its own sample-to-sample motion (a gyro frame corrupted past its checksum, a
DS18B20 reading its power-on 85.0 C or 127.94 C, a logger writing a stale or garbled value).

Method (a Hampel filter along the local line, with a motion allowance).  On each contiguous piece of
the record (split at non-finite values, at gaps longer than ``GAP_PERIODS`` sample periods and where
a label such as the orientation changes), every sample's deviation from the robust local line of the
``WINDOW`` samples around it (slope: their median first difference; level: their median carried to
the sample along it; the first or last whole window within half a window of an end, so a glitch on a
piece's first reading is found) is compared with two scales:

* the noise: 1.4826 x the median absolute deviation from the running median of ``WINDOW`` samples,
  the larger of the whole record's and the ``NOISE_WINDOW`` samples' around it (a noisier stretch is
  judged by its own noise), and at least half the typical non-zero deviation (quantised data whose
  deviations are mostly exactly zero);
* the motion: the median absolute first difference over the window (a sharp reversal of a fast ramp
  leaves its peak about 2.5 differences from the median; a spike leaves it by much more while most
  differences around it stay small).

A sample is a glitch when its deviation exceeds ``K_NOISE`` noise scales and ``K_MOTION`` motion
scales, when jumps of half its size are rare within ``NOISE_WINDOW`` samples around it (a signal that
steps between a few levels, such as one derived from a quantised probe whose last bit toggles, makes
them all the time), and when it exceeds a caller's minimum size (for a temperature, what no probe on
a thermal mass does in one reading).  The local line follows ramps, steps and any locally monotone
course, so bias steps, warm-ups and mode hops are not glitches; up to half a window of consecutive bad
samples is found.  Gaussian noise exceeds 10 sigma about once in 10^23 samples; DS18B20 readings
averaged over a logging period, whose deviations are mostly exactly zero, reach 8 of their robust
sigmas now and then.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

from bench.signal.segments import run_segments

WINDOW = 11            # samples in the running median (finds up to 5 consecutive bad samples)
NOISE_WINDOW = 101     # samples over which the local noise scale is taken
K_NOISE = 10.0         # a glitch deviates by more than this many robust sigmas ...
K_MOTION = 5.0         # ... and by more than this many median first differences around it
MAX_LIKE_JUMPS = 4     # ... and jumps of its size are rare around it (a burst's two edges, a pair of glitches)
GAP_PERIODS = 5.0      # a time step longer than this many median sample periods splits the record
MAD_TO_SIGMA = 1.4826


def _pieces(time_s: np.ndarray, ok: np.ndarray, labels: np.ndarray | None) -> list[np.ndarray]:
    """Index arrays of the contiguous pieces of ``ok`` samples (``run_segments`` over them: split at
    long time gaps and where ``labels``, e.g. a multi-position test's orientation, change), split also
    where a sample is not ``ok``."""
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return []
    key = np.concatenate([[0], np.cumsum(np.diff(idx) > 1)])
    if labels is not None:
        _, code = np.unique(np.asarray(labels)[idx], return_inverse=True)
        key = key * (int(code.max()) + 1) + code
    return [idx[s] for s in run_segments(time_s[idx], key, GAP_PERIODS)]


def _windows(n: int, at: np.ndarray) -> np.ndarray:
    """(len(at), WINDOW) sample numbers of the window judging each sample ``at``: centred on it, or the
    first or last whole window for the samples within half a window of an end."""
    first = np.clip(at - WINDOW // 2, 0, n - WINDOW)
    return first[:, None] + np.arange(WINDOW)[None, :]


def _off_local_line(x: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At samples ``at``: the deviation from the robust local line (slope: the median first difference
    over the window; level: the median of the window's samples carried to the sample along that slope)
    and the median absolute first difference over the window (its motion).  At the ends the line of
    the end window is extrapolated, so a ramp running into an end is followed as in the middle."""
    win = _windows(len(x), at)
    signed = np.diff(x[win], axis=1)
    slope = np.median(signed, axis=1)
    level = np.median(x[win] - slope[:, None] * (win - at[:, None]), axis=1)
    return x[at] - level, np.median(np.abs(signed), axis=1)


def _rare_jumps(x: np.ndarray, at: np.ndarray, size: np.ndarray) -> np.ndarray:
    """At samples ``at`` off the local line by ``size``: whether a jump of half that size is rare
    around them (at most ``MAX_LIKE_JUMPS`` first differences within ``NOISE_WINDOW`` samples, the
    sample's own two left out).  A signal that steps between a few levels (a derived quantity that
    follows a quantised probe, its last bit toggling) makes such jumps all the time; a glitch does not."""
    steps = np.abs(np.diff(x))
    half = NOISE_WINDOW // 2
    keep = np.zeros(len(at), dtype=bool)
    for k, (i, d) in enumerate(zip(at, size)):
        lo, hi = max(i - half, 0), min(i + half, len(steps))
        near = steps[lo:hi] > 0.5 * d
        own = [j - lo for j in (i - 1, i) if lo <= j < hi]
        near[own] = False
        keep[k] = int(near.sum()) <= MAX_LIKE_JUMPS
    return keep


def isolated_glitches(time_s: np.ndarray, x: np.ndarray, min_deviation: float = 0.0,
                      labels: np.ndarray | None = None) -> np.ndarray:
    """True where a sample of ``x`` (sampled at ``time_s`` seconds) is an isolated glitch (module
    docstring), and off the local line by more than ``min_deviation`` (in the units of ``x``) too.
    ``labels`` (one per sample, e.g. the orientation of a multi-position test) split the record where
    they change: a position held for one sample is not a glitch of the position before.  Non-finite
    samples are never glitches (they are missing already); pieces shorter than ``WINDOW`` samples
    are not judged."""
    t = np.asarray(time_s, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    out = np.zeros(len(x), dtype=bool)
    pieces = [p for p in _pieces(t, np.isfinite(x) & np.isfinite(t), labels) if len(p) >= WINDOW]
    if not pieces:
        return out
    # the noise scales from the deviations off the running median (the local line's, but for the ends)
    dev = [x[p] - median_filter(x[p], size=WINDOW, mode="mirror") for p in pieces]
    absdev = np.abs(np.concatenate(dev))
    nonzero = absdev[absdev > 0]
    floor = max(MAD_TO_SIGMA * float(np.median(absdev)),
                0.5 * float(np.median(nonzero)) if len(nonzero) else 0.0)
    if not floor > 0:
        return out                                   # a constant signal has no glitch
    for p, d in zip(pieces, dev):
        local = MAD_TO_SIGMA * median_filter(np.abs(d), size=min(NOISE_WINDOW, len(p)), mode="mirror")
        scale = K_NOISE * np.maximum(local, floor)
        # the local line only where the running median already puts a sample far off (few samples)
        at = np.flatnonzero(np.abs(d) > 0.5 * np.maximum(scale, min_deviation))
        if len(at):
            off, motion = _off_local_line(x[p], at)
            big = ((np.abs(off) > scale[at]) & (np.abs(off) > K_MOTION * motion)
                   & (np.abs(off) > min_deviation))
            out[p[at[big]]] = _rare_jumps(x[p], at[big], np.abs(off[big]))
    return out

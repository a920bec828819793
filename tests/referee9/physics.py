"""Referee 9 physics: thermal network, gyro noise, Earth rate / gravity, effect columns, 100-s blocks.

Written from the physics notes only (nothing imported from ``bench``).  Units: time s, temperature C,
gyro deg/h, rates C/min.
"""
from __future__ import annotations

import itertools

import numpy as np

OMEGA_IE_DPH = 7.2921158553e-5 * 180.0 / np.pi * 3600.0  # 15.041 deg/h
BLOCK_S = 100.0

# ---------------------------------------------------------------------------------------------
# orientation (three letters: directions of body x, y, z in E W N S U D, right-handed)
_DIR = {"E": (1, 0, 0), "W": (-1, 0, 0), "N": (0, 1, 0), "S": (0, -1, 0), "U": (0, 0, 1), "D": (0, 0, -1)}


def right_handed_codes():
    out = []
    for a, b, c in itertools.permutations("ENU", 3):
        for sa, sb, sc in itertools.product((1, -1), repeat=3):
            va = np.array(_DIR[a]) * sa
            vb = np.array(_DIR[b]) * sb
            vc = np.array(_DIR[c]) * sc
            if np.allclose(np.cross(va, vb), vc):
                name = "".join(_letter(v) for v in (va, vb, vc))
                out.append(name)
    return sorted(out)


def _letter(v):
    for k, d in _DIR.items():
        if tuple(int(x) for x in v) == d:
            return k
    raise ValueError(v)


def axis_vectors(code):
    """ENU unit vectors of body x, y, z for an orientation code."""
    return np.array([_DIR[c] for c in code], dtype=float)


def earth_rate_body(code, lat_deg):
    """Earth rate (deg/h) seen by body axes x, y, z; Earth rate in ENU is Omega*(0, cos phi, sin phi)."""
    phi = np.radians(lat_deg)
    w = OMEGA_IE_DPH * np.array([0.0, np.cos(phi), np.sin(phi)])
    return axis_vectors(code) @ w


def gravity_body(code):
    """Specific force (units of g) along body axes in a static position: +1 g up."""
    return axis_vectors(code) @ np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------------------------
# signals

def lag(x, tau, dt=1.0, x0=None):
    """First-order lag on a uniform grid (ramp-invariant exact step for a piecewise-linear input),
    starting at rest at x[0] (or x0)."""
    from scipy.signal import lfilter
    x = np.asarray(x, float)
    a = np.exp(-dt / tau)
    b = tau / dt * (1 - a)
    num, den = [1 - b, b - a], [1.0, -a]
    y0 = x[0] if x0 is None else x0
    # state so that y[0] = y0 with x[-1] = x[0]
    zi = np.array([y0 - (1 - b) * x[0]])
    y, _ = lfilter(num, den, x, zi=zi)
    return y


def lag_irregular(t, x, tau):
    """First-order lag of samples x at times t (NaN filled by interpolation), ramp-invariant steps."""
    x = fill_nan(t, x)
    y = np.empty_like(x)
    y[0] = x[0]
    dts = np.diff(t)
    a = np.exp(-dts / tau)
    b = tau / dts * (1 - a)
    for k in range(len(x) - 1):
        y[k + 1] = a[k] * y[k] + (1 - b[k]) * x[k + 1] + (b[k] - a[k]) * x[k]
    return y


def fill_nan(t, x):
    x = np.asarray(x, float)
    m = np.isfinite(x)
    if m.all():
        return x.copy()
    return np.interp(t, t[m], x[m])


def centred_slope(t, x, window_s=120.0):
    """Centred least-squares slope of x over window_s seconds (C/min), valid samples only."""
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    m = np.isfinite(x)
    tt = t - t[0]
    w = m.astype(float)
    xv = np.where(m, x, 0.0)
    c = lambda v: np.concatenate([[0.0], np.cumsum(v)])
    S0, S1, S2 = c(w), c(w * tt), c(w * tt * tt)
    Sx, Stx = c(xv), c(xv * tt)
    lo = np.searchsorted(tt, tt - window_s / 2, side="left")
    hi = np.searchsorted(tt, tt + window_s / 2, side="right")
    n = S0[hi] - S0[lo]
    st = S1[hi] - S1[lo]
    stt = S2[hi] - S2[lo]
    sx = Sx[hi] - Sx[lo]
    stx = Stx[hi] - Stx[lo]
    den = stt - st * st / np.maximum(n, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (stx - st * sx / np.maximum(n, 1)) / den
    s = np.where((n >= 3) & (den > 0), s, np.nan)
    return fill_nan(t, s) * 60.0


def flicker(rng, n, dt, sigma_b, taus=None):
    """Approximate 1/f noise: AR(1) processes with log-spaced time constants of equal variance.
    sigma_b ~ the flat part of the Allan deviation (bias instability level, deg/h)."""
    if taus is None:
        taus = np.logspace(np.log10(20.0), np.log10(2e5), 16)
    out = np.zeros(n)
    # each octave-ish component carries the same variance -> flat ADEV over the covered band
    s = sigma_b / np.sqrt(len(taus)) * 2.2
    for tau in taus:
        a = np.exp(-dt / tau)
        e = rng.normal(0.0, s * np.sqrt(1 - a * a), n)
        e[0] = rng.normal(0.0, s)
        out += _ar1(e, a)
    return out


def _ar1(e, a):
    from scipy.signal import lfilter
    return lfilter([1.0], [1.0, -a], e)


def gyro_noise(rng, n, dt, white, flick, rrw):
    """white: std per 1-s sample (deg/h); flick: bias-instability level; rrw: deg/h per sqrt(h)."""
    w = rng.normal(0.0, white / np.sqrt(dt), n)
    f = flicker(rng, n, dt, flick)
    r = np.cumsum(rng.normal(0.0, rrw * np.sqrt(dt / 3600.0), n))
    return w + f + r - r.mean()


# ---------------------------------------------------------------------------------------------
# chamber program and thermal network (1-s grid)

def program(segments, t_start, dt=1.0):
    """segments: list of (target C, ramp C/min, soak s); starts at t_start C.  Returns set point."""
    sp = [t_start]
    cur = t_start
    for target, ramp, soak in segments:
        nr = int(round(abs(target - cur) / (ramp / 60.0) / dt))
        if nr > 0:
            sp.extend(np.linspace(cur, target, nr + 1)[1:])
        sp.extend([target] * int(round(soak / dt)))
        cur = target
    return np.array(sp, float)


def network(sp, rng, par, dt=1.0):
    """Lumped network: chamber air follows the set point; case, three sensing elements, base plate,
    mount.  par: dict of time constants.  Returns dict of true node temperatures."""
    n = len(sp)
    air = lag(sp, par["air"], dt)
    # compressor / heater ripple on the air (small, period ~ 4-7 min)
    ph = rng.uniform(0, 2 * np.pi)
    air = air + par.get("ripple", 0.05) * np.sin(2 * np.pi * np.arange(n) * dt / par.get("ripple_p", 330.0) + ph)
    base = lag(air, par["base"], dt)
    case = lag(0.7 * air + 0.3 * base, par["case"], dt)
    mount = lag(0.5 * base + 0.5 * air, par["mount"], dt)
    elems = [lag(case, te, dt) + off for te, off in zip(par["elem"], par["elem_off"])]
    return dict(air=air, base=base, case=case, mount=mount, e=elems)


def ds18b20(x):
    return np.round(np.asarray(x) * 16.0) / 16.0


def fine_probe(rng, x, noise=0.003, q=0.001):
    return np.round((x + rng.normal(0, noise, len(x))) / q) * q


# ---------------------------------------------------------------------------------------------
# 100-s blocks

def block_ids(t):
    return np.floor((np.asarray(t) - t[0]) / BLOCK_S).astype(int)


def block_means(ids, y, valid=None):
    y = np.asarray(y, float)
    m = np.isfinite(y) if valid is None else (valid & np.isfinite(y))
    nb = ids.max() + 1
    s = np.bincount(ids[m], weights=y[m], minlength=nb)
    c = np.bincount(ids[m], minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / c, c


def std100(t, r, block_mask=None, min_count=None):
    ids = block_ids(t)
    bm, c = block_means(ids, r)
    full = np.bincount(ids, minlength=ids.max() + 1)
    ok = (c >= 0.5 * np.maximum(full, 1)) & (c > 0)
    if block_mask is not None:
        ok &= block_mask
    v = bm[ok]
    if len(v) < 3:
        return float("nan")
    return float(np.std(v - v.mean()))


def lstsq_blocks(t, y, cols, valid):
    """Least squares of y on [1, cols...] using 100-s block means over valid samples."""
    ids = block_ids(t)
    ym, c = block_means(ids, y, valid)
    full = np.bincount(ids, minlength=ids.max() + 1)
    ok = (c >= 0.5 * np.maximum(full, 1)) & (c > 0)
    X = [np.ones(ok.sum())]
    for col in cols:
        cm, _ = block_means(ids, col, valid & np.isfinite(col))
        X.append(cm[ok])
    X = np.column_stack(X)
    good = np.all(np.isfinite(X), axis=1) & np.isfinite(ym[ok])
    sc = np.maximum(np.abs(X[good]).max(axis=0), 1e-12)
    beta, *_ = np.linalg.lstsq(X[good] / sc, ym[ok][good], rcond=None)
    return beta / sc


def predict(beta, cols, n):
    p = np.full(n, beta[0])
    for b, col in zip(beta[1:], cols):
        p = p + b * col
    return p

"""Physics for referee 6: chamber profiles, a lumped thermal network, DS18B20 probes,
FOG noise (white + flicker + rate random walk) and the effect columns.

Conventions are this referee's own; nothing here is shared with the product.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter

# ----------------------------------------------------------------------------- chamber profile

def chamber_profile(rng, duration_s, lo, hi, rate_range=(0.5, 3.0), start=None,
                    soak_range=(900.0, 4200.0), n_partial=1):
    """Piecewise-linear setpoint (knots t, v): soaks and ramps between lo and hi, reversals.

    Starts at `start` (default room temperature clipped to [lo, hi]); alternates going to the cold
    and hot ends, with `n_partial` partial reversals (ramp turns back mid-way) thrown in.
    """
    t = [0.0]
    v = [float(np.clip(25.0 if start is None else start, lo, hi))]
    t.append(float(rng.uniform(600, 1800)))
    v.append(v[-1])                                      # initial soak
    go_hot = bool(rng.integers(2))
    partial_left = n_partial
    while t[-1] < duration_s:
        end = hi if go_hot else lo
        if partial_left > 0 and rng.random() < 0.4:
            end = v[-1] + (end - v[-1]) * rng.uniform(0.35, 0.7)
            partial_left -= 1
        rate = rng.uniform(*rate_range) / 60.0           # C/s
        dur = abs(end - v[-1]) / rate
        if dur < 60:
            go_hot = not go_hot
            continue
        t.append(t[-1] + dur)
        v.append(float(end))
        t.append(t[-1] + rng.uniform(*soak_range))
        v.append(float(end))
        go_hot = not go_hot
    return np.array(t), np.array(v)


# ----------------------------------------------------------------------------- thermal network

NODES = ["air", "mount", "case_x", "case_y", "cover", "elem_own", "elem_other", "elem_long", "internal"]


def make_network(rng, *, own_node="case_x", other_node="cover", tau_own=600.0, tau_other=600.0,
                 tau_long=20000.0):
    """Draw one device's lumped network (continuous-time A, B). Nodes: see NODES.

    air    <- chamber wall (setpoint) with tau_air
    mount  <- air (large capacity); case_x, case_y <- mount + air; cover <- air + mount
    elem_*  : gyro element nodes, each coupled by ONE conductance to ONE node (so each is an exact
              first-order lag of that node's temperature).
    internal: an unprobed node coupled to mount and heated by an input no column records.
    """
    n = len(NODES)
    idx = {k: i for i, k in enumerate(NODES)}
    A = np.zeros((n, n))
    B = np.zeros((n, 2))        # inputs: setpoint, heat

    def couple(a, b, rate_a):
        A[idx[a], idx[a]] -= rate_a
        A[idx[a], idx[b]] += rate_a

    tau_air = rng.uniform(90, 240)
    A[0, 0] -= 1 / tau_air
    B[0, 0] = 1 / tau_air
    couple("mount", "air", 1 / rng.uniform(900, 2400))
    # distinct mixes so that no probe is (nearly) a pure lag of another one: case_x sits on the
    # mount, case_y is mounted on a bracket in the air stream, the cover sees air and mount
    couple("case_x", "mount", 1 / rng.uniform(300, 900))
    couple("case_x", "air", 1 / rng.uniform(1500, 5000))
    couple("case_y", "mount", 1 / rng.uniform(600, 1500))
    couple("case_y", "air", 1 / rng.uniform(400, 1000))
    couple("cover", "air", 1 / rng.uniform(300, 800))
    couple("cover", "mount", 1 / rng.uniform(500, 1200))
    couple("elem_own", own_node, 1 / tau_own)
    couple("elem_other", other_node, 1 / tau_other)
    couple("elem_long", own_node, 1 / tau_long)
    couple("internal", "mount", 1 / rng.uniform(1500, 3000))
    B[idx["internal"], 1] = 1.0
    return A, B


def integrate(A, B, t_grid, sp, heat=None):
    """Exact zero-order-hold integration on a uniform grid, starting in equilibrium at sp[0]."""
    n = A.shape[0]
    h = float(t_grid[1] - t_grid[0])
    M = np.zeros((n + 2, n + 2))
    M[:n, :n] = A * h
    M[:n, n:] = B * h
    E = expm(M)
    Ad, Bd = E[:n, :n], E[:n, n:]
    q = np.zeros_like(sp) if heat is None else heat
    U = np.column_stack([sp, q]) @ Bd.T
    x = np.full(n, sp[0])
    out = np.empty((len(t_grid), n))
    for k in range(len(t_grid)):       # tight loop, small matrix
        out[k] = x
        x = Ad @ x + U[k]
    return {k: out[:, i] for i, k in enumerate(NODES)}


def first_order(x, h, tau):
    """Exact first-order lag of a sampled signal (step h), starting in equilibrium."""
    a = np.exp(-h / tau)
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    return y


def ds18b20(true_t, h, tau, offset):
    """What a DS18B20 reports: own small lag (tau 2-6 s), small offset; 0.0625 C quantisation.
    Returns (sensed before quantisation, reported)."""
    sensed = first_order(true_t, h, tau) + offset
    return sensed, np.round(sensed / 0.0625) * 0.0625


# ----------------------------------------------------------------------------- noise

def fog_noise(rng, n, h, white_1s, flicker, rrw=0.0):
    """White (deg/h at 1 s) + flicker (sum of AR(1) over decades, each std `flicker`)
    + rate random walk (deg/h per sqrt(h))."""
    y = rng.standard_normal(n) * white_1s / np.sqrt(h)
    for tau in (10.0, 100.0, 1000.0, 10000.0, 60000.0):
        if tau < h:
            continue
        a = np.exp(-h / tau)
        drive = rng.standard_normal(n) * flicker * np.sqrt(1 - a * a)
        z, _ = lfilter([1.0], [1, -a], drive, zi=[a * flicker * rng.standard_normal()])
        y += z
    if rrw > 0:
        y += np.cumsum(rng.standard_normal(n)) * rrw * np.sqrt(h / 3600.0)
    return y


# ----------------------------------------------------------------------------- effect columns

def rate(x, t, conv):
    """dT/dt in C/s, by this case's convention: 'grad' | 'sm30' | 'sm300'."""
    if conv != "grad":
        h = t[1] - t[0]
        w = max(1, int(round(float(conv[2:]) / h)))
        k = np.ones(w) / w
        pad = np.concatenate([np.full(w, x[0]), x, np.full(w, x[-1])])
        x = np.convolve(pad, k, mode="same")[w:-w]
    return np.gradient(x, t)


def _first_move(x, width):
    """+1 if the signal first leaves x[0] +- width upward, -1 if downward (+1 if never)."""
    d = x - x[0]
    up = np.flatnonzero(d > width)
    dn = np.flatnonzero(d < -width)
    if len(dn) and (not len(up) or dn[0] < up[0]):
        return -1.0
    return 1.0


def relay(x, width):
    """State +1/-1, switches after the temperature reverses by `width` from its last extremum."""
    s = np.empty(len(x))
    state = _first_move(x, width)      # as if the device arrived from the other side
    ext = x[0]
    for i, v in enumerate(x):
        if state > 0:
            if v > ext:
                ext = v
            elif v < ext - width:
                state, ext = -1.0, v
        else:
            if v < ext:
                ext = v
            elif v > ext + width:
                state, ext = 1.0, v
        s[i] = state
    return s


def play(x, width):
    """Play (backlash) operator of total width `width`, output minus input (in C)."""
    p = np.empty(len(x))
    hw = width / 2
    cur = x[0] - _first_move(x, hw) * hw   # arrived from the other side: output engaged at once
    for i, v in enumerate(x):
        if v > cur + hw:
            cur = v - hw
        elif v < cur - hw:
            cur = v + hw
        p[i] = cur
    return p - x


def schmitt(x, up, down):
    """Mode hop: mode 1 above `up` until it falls below `down` (fixed thresholds)."""
    s = np.empty(len(x))
    m = 1.0 if x[0] > up else 0.0
    for i, v in enumerate(x):
        if m == 0.0 and v > up:
            m = 1.0
        elif m == 1.0 and v < down:
            m = 0.0
        s[i] = m
    return s


def std100(t, r, ok, expected_per_block):
    """Std of 100-s block means of r over samples `ok`; blocks need >= half their samples."""
    b = np.floor((t - t[0]) / 100.0).astype(int)
    b = b[ok]
    rr = r[ok]
    if len(rr) == 0:
        return float("nan"), 0
    cnt = np.bincount(b)
    sm = np.bincount(b, weights=rr)
    good = cnt >= 0.5 * expected_per_block
    if good.sum() < 3:
        return float("nan"), int(good.sum())
    m = sm[good] / cnt[good]
    return float(np.std(m, ddof=1)), int(good.sum())

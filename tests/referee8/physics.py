"""Referee 8 physics: chamber program -> lumped thermal network -> DS18B20-like probes, gyro noise.

Conventions of this lab (see NOTES.md):
* time grid t = 0, dt, 2dt, ... from the first logged row; the simulation starts PRE_S before it.
* the thermal network is linear, driven by the chamber set-point (piecewise linear in time) and the
  electronics heat (piecewise constant, on while powered); it is stepped exactly on the sample grid
  with the ramp-invariant (first-order-hold) discretisation of the whole state vector.
* states: air, baseplate, housing, mount_x, mount_y, mount_z, electronics, and one die state per
  probe (the probe's own glue lag behind the node it sits on).
* a probe reading = die temperature + offset + white read noise, rounded to 1/16 C.
* "noiseless reading" (what an ideal analysis of the CSV could reconstruct) = die + offset: the
  truth's declared part and its effect columns are built on it (or on hidden nodes, say which).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm

EARTH_RATE_DPH = 15.041067
NODES = ["air", "base", "housing", "mount_x", "mount_y", "mount_z", "elec"]


def _network(rng_params):
    """Return (A, Bsp, Bpow, names) for the 7 physical nodes (rows are dT/dt in C/s)."""
    p = rng_params
    C = {"air": p["c_air"], "base": p["c_base"], "housing": p["c_housing"], "mount_x": p["c_mount"],
         "mount_y": p["c_mount"] * 1.15, "mount_z": p["c_mount"] * 0.85, "elec": p["c_elec"]}
    links = [("air", "base", p["g_air_base"]), ("air", "housing", p["g_air_housing"]),
             ("base", "housing", p["g_base_housing"]), ("housing", "mount_x", p["g_mount"]),
             ("housing", "mount_y", p["g_mount"] * 0.8), ("housing", "mount_z", p["g_mount"] * 1.1),
             ("base", "mount_z", p["g_mount"] * 0.35), ("base", "mount_y", p["g_mount"] * 0.2),
             ("housing", "elec", p["g_elec"]), ("mount_x", "elec", p["g_elec"] * 0.3)]
    n = len(NODES)
    idx = {k: i for i, k in enumerate(NODES)}
    G = np.zeros((n, n))
    for a, b, g in links:
        i, j = idx[a], idx[b]
        G[i, j] += g
        G[j, i] += g
    A = np.zeros((n, n))
    for i, k in enumerate(NODES):
        A[i, :] = G[i, :] / C[k]
        A[i, i] = -G[i, :].sum() / C[k]
    # the chamber controller holds the air: it follows the set-point with time constant tau_air and
    # the unit's heat exchange does not disturb it (a chamber is far larger than the unit)
    A[0, :] = 0.0
    A[0, 0] = -1.0 / p["tau_air"]
    Bsp = np.zeros(n)
    Bsp[0] = 1.0 / p["tau_air"]
    Bpow = np.zeros(n)
    Bpow[idx["elec"]] = p["heat_w"] / C["elec"]
    return A, Bsp, Bpow


def default_network_params(rng):
    return {
        "c_air": 60.0, "tau_air": rng.uniform(60, 140),
        "c_base": rng.uniform(7000, 12000), "c_housing": rng.uniform(1800, 3200),
        "c_mount": rng.uniform(250, 450), "c_elec": rng.uniform(300, 500),
        "g_air_base": rng.uniform(4, 8), "g_air_housing": rng.uniform(2.5, 5),
        "g_base_housing": rng.uniform(2, 4), "g_mount": rng.uniform(1.8, 3.2),
        "g_elec": rng.uniform(0.8, 1.6), "heat_w": rng.uniform(1.0, 2.5),
    }


def simulate_network(params, probe_sites, glue_tau, t, sp, power, pre_s=0.0, sp_pre=None):
    """Step the network exactly (FOH on the set-point, ZOH on the power) on grid t.

    probe_sites: list of node names per probe; glue_tau: list of die time constants (s).
    sp, power: arrays on t. pre_s: seconds simulated before t[0] (set-point sp_pre(t) there, power
    off), starting from equilibrium at sp_pre(-pre_s).
    Returns dict node -> array, and 'die' array (n_probes, len(t)).
    """
    A0, Bsp0, Bpow0 = _network(params)
    n0 = len(NODES)
    npr = len(probe_sites)
    n = n0 + npr
    A = np.zeros((n, n))
    A[:n0, :n0] = A0
    for k, (site, tg) in enumerate(zip(probe_sites, glue_tau)):
        A[n0 + k, NODES.index(site)] = 1.0 / tg
        A[n0 + k, n0 + k] = -1.0 / tg
    Bsp = np.zeros(n)
    Bsp[:n0] = Bsp0
    Bpow = np.zeros(n)
    Bpow[:n0] = Bpow0

    dt = float(t[1] - t[0])
    # augmented system for FOH: state [x, u_sp, du_sp/dt, pow]
    M = np.zeros((n + 3, n + 3))
    M[:n, :n] = A
    M[:n, n] = Bsp
    M[:n, n + 2] = Bpow
    M[n, n + 1] = 1.0
    E = expm(M * dt)
    Ad = E[:n, :n]
    Bu = E[:n, n]
    Bdu = E[:n, n + 1]
    Bp = E[:n, n + 2]

    # equilibrium at the start of the pre-history (power off)
    if sp_pre is None:
        sp_pre = lambda tt: np.full_like(np.asarray(tt, float), sp[0])
    x = -np.linalg.solve(A, Bsp * float(sp_pre(np.array([-pre_s]))[0]))
    pre_die = [x[n0:].copy()]
    if pre_s > 0:
        tp = np.arange(-pre_s, 0.0 + 1e-9, dt)
        spp = sp_pre(tp)
        for k in range(len(tp) - 1):
            slope = (spp[k + 1] - spp[k]) / dt
            x = Ad @ x + Bu * spp[k] + Bdu * slope
            pre_die.append(x[n0:].copy())
    X = np.empty((len(t), n))
    X[0] = x
    for k in range(len(t) - 1):
        slope = (sp[k + 1] - sp[k]) / dt
        x = Ad @ x + Bu * sp[k] + Bdu * slope + Bp * power[k]
        X[k + 1] = x
    out = {name: X[:, i] for i, name in enumerate(NODES)}
    out["die"] = X[:, n0:].T.copy()
    out["pre_die"] = np.array(pre_die[:-1]).T     # die history before the first row (same grid)
    return out


def first_order_lag(u, dt, tau, y0=None):
    """Exact ramp-invariant first-order lag of u (linear between samples)."""
    a = np.exp(-dt / tau)
    b1 = 1.0 - tau / dt * (1.0 - a)       # weight on the new sample
    b0 = (1.0 - a) - b1                    # weight on the old one
    y = np.empty_like(u)
    y[0] = u[0] if y0 is None else y0
    for k in range(len(u) - 1):
        y[k + 1] = a * y[k] + b0 * u[k] + b1 * u[k + 1]
    return y


def play_operator(u, r, y0):
    """Backlash (play) of half-width r: output follows u only when |u-y| > r."""
    y = np.empty_like(u)
    yk = y0
    for k, uk in enumerate(u):
        if uk > yk + r:
            yk = uk - r
        elif uk < yk - r:
            yk = uk + r
        y[k] = yk
    return y


def smooth_rate(u, dt, window_s):
    """dT/dt (C/s) as the centred slope of a window: a physical rate (noise-free input expected)."""
    h = max(1, int(round(window_s / dt / 2)))
    d = np.empty_like(u)
    d[h:-h] = (u[2 * h:] - u[:-2 * h]) / (2 * h * dt)
    d[:h] = d[h]
    d[-h:] = d[-h - 1]
    return d


def probe_readings(die, offsets, noise_c, rng, quant=0.0625):
    raw = die + offsets[:, None] + rng.normal(0.0, 1.0, die.shape) * noise_c[:, None]
    return np.round(raw / quant) * quant


def gyro_noise(n, dt, rng, arw_dpsh, bi_dph, rrw_dphsh, lowpass_s=0.0):
    """White (ARW) + flicker (sum of Gauss-Markov terms, 2 per decade 3 s .. 3e4 s) + RRW, deg/h."""
    white = rng.normal(0.0, arw_dpsh * 60.0 / np.sqrt(dt), n)
    if lowpass_s > 0:
        a = np.exp(-dt / lowpass_s)
        # keep the long-term density: unity DC gain
        from scipy.signal import lfilter
        white = lfilter([1 - a], [1, -a], white)
    flick = np.zeros(n)
    taus = np.logspace(np.log10(3.0), np.log10(3e4), 9)
    from scipy.signal import lfilter
    for tau in taus:
        a = np.exp(-dt / tau)
        s = bi_dph * 0.42
        e = rng.normal(0.0, s * np.sqrt(1 - a * a), n)
        g = lfilter([1.0], [1.0, -a], e)
        g += s * rng.normal() * a ** np.arange(n)   # stationary start
        flick += g
    rrw = np.cumsum(rng.normal(0.0, rrw_dphsh * np.sqrt(dt / 3600.0), n))
    return white + flick + rrw


def block_means(t, y, block_s=100.0, valid=None):
    """Means over 100-s blocks counted from t[0]; returns (block index array, means, counts)."""
    b = np.floor((t - t[0]) / block_s + 1e-9).astype(int)
    ok = np.isfinite(y) if valid is None else (valid & np.isfinite(y))
    nb = b.max() + 1
    s = np.bincount(b[ok], weights=y[ok], minlength=nb)
    c = np.bincount(b[ok], minlength=nb)
    full = np.bincount(b, minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = s / c
    good = c >= 0.5 * full
    m[~good] = np.nan
    return m, c


def std100(t, y, valid=None):
    m, _ = block_means(t, y, valid=valid)
    m = m[np.isfinite(m)]
    return float(np.std(m, ddof=1)) if len(m) > 2 else float("nan")

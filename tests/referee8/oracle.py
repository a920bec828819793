"""Referee 8 oracle: declared terms (on the recorded own-probe readings) + the TRUE effect columns,
least squares on TRAIN 100-s block means, judged on VALIDATE in-range 100-s blocks.

Also the look-alike check: the product's named effects rebuilt with this lab's own columns (their
continuous parameters searched finely) must reproduce the true noiseless signal on TRAIN within half
a noise floor of what the true columns do.
"""
from __future__ import annotations

import numpy as np

from . import physics as ph
from .cases import T_REF, CHANNELS


def declared(run, probe):
    x = run.temps[probe] - T_REF
    return [x, x ** 2, x ** 3]


def _bm_matrix(t, cols, valid):
    return np.column_stack([ph.block_means(t, c, valid=valid)[0] for c in cols])


def fit_blocks(t, y, cols, valid):
    Y = ph.block_means(t, y, valid=valid)[0]
    X = _bm_matrix(t, cols, valid)
    ok = np.isfinite(Y) & np.all(np.isfinite(X), axis=1)
    A = np.column_stack([np.ones(ok.sum()), X[ok]])
    beta, *_ = np.linalg.lstsq(A, Y[ok], rcond=None)
    return beta


def predict(beta, cols):
    return beta[0] + sum(b * c for b, c in zip(beta[1:], cols))


def in_range_valid(case, ch):
    """Samples of VALIDATE (powered) in 100-s blocks whose declared input stays in TRAIN's range."""
    p = case.channel_probes[ch]
    tr, va = case.train, case.validate
    on_tr = tr.power > 0.5
    lo, hi = np.nanmin(tr.temps[p][on_tr]), np.nanmax(tr.temps[p][on_tr])
    b = np.floor((va.t - va.t[0]) / 100.0 + 1e-9).astype(int)
    T = va.temps[p]
    outside = (T < lo) | (T > hi)
    bad_blocks = np.unique(b[outside])
    ok = ~np.isin(b, bad_blocks)
    return ok & (va.power > 0.5)


def oracle(case, ch):
    tr, va = case.train, case.validate
    p = case.channel_probes[ch]
    eff = case.truth[ch]["effects"]
    cols_tr = declared(tr, p) + [e["cols"]["train"] for e in eff]
    cols_va = declared(va, p) + [e["cols"]["validate"] for e in eff]
    vtr = tr.power > 0.5
    beta = fit_blocks(tr.t, tr.gyro[ch], cols_tr, vtr)
    res = va.gyro[ch] - predict(beta, cols_va)
    ok = in_range_valid(case, ch)
    # the declared model alone (before), for reference
    b0 = fit_blocks(tr.t, tr.gyro[ch], declared(tr, p), vtr)
    res0 = va.gyro[ch] - predict(b0, declared(va, p))
    return dict(oracle=ph.std100(va.t, res, valid=ok), before=ph.std100(va.t, res0, valid=ok),
                noise=ph.std100(va.t, va.noise[ch], valid=ok), coverage=float(ok.mean()))


# ----------------------------------------------------------------------------- look-alikes
TAUS = np.unique(np.concatenate([np.geomspace(60, 80000, 90)]))


def _lib_columns(run, kind, params, own, dt, tau=None, win=120.0):
    """This lab's version of a product library effect (one family, parameters given)."""
    probe = params.get("probe")
    probes = params.get("probes") or params.get("pair")
    if isinstance(probes, str):
        probes = probes.split("-")
    if kind == "thermal_lag":
        T = run.temps[probe]
        L = ph.first_order_lag(T, dt, tau)
        return [L] if params.get("form") == "absolute" else [L - T]
    if kind == "gradient":
        a, b = probes
        return [run.temps[a] - run.temps[b]]
    if kind in ("rate", "rate_squared", "temp_rate_cross"):
        T = _smooth(run.temps[probe], dt, win)
        d = np.gradient(T, dt)
        if kind == "rate":
            return [d]
        if kind == "rate_squared":
            return [d ** 2]
        return [(T - 25.0) * d, d]
    if kind == "time_drift":
        return [run.t]
    if kind == "warmup":
        on = run.power > 0.5
        ts = np.zeros_like(run.t)
        last = 0.0
        for i in range(len(run.t)):
            if i > 0 and on[i] and not on[i - 1]:
                last = run.t[i]
            ts[i] = run.t[i] - last
        return [np.exp(-ts / tau)]
    return None


def _smooth(x, dt, w):
    n = max(1, int(round(w / dt)))
    k = np.ones(n) / n
    y = np.convolve(x, k, mode="same")
    y[: n // 2] = y[n // 2]
    y[-(n // 2) - 1:] = y[-(n // 2) - 1]
    return y


NEEDS_TAU = {"thermal_lag", "warmup"}


def lookalike(case, ch, added):
    """(ok, excess_dph, floor_dph): do the product's named effects imitate the truth on TRAIN?"""
    tr = case.train
    own = case.channel_probes[ch]
    valid = tr.power > 0.5
    clean_signal = tr.declared_true[ch] + sum(tr.effects[ch], np.zeros_like(tr.t))
    decl = declared(tr, own)
    floor = case.truth[ch]["effects"][0]["floor_train"] if case.truth[ch]["effects"] else ph.std100(
        tr.t, tr.noise[ch], valid=valid)
    true_cols = decl + [e["cols"]["train"] for e in case.truth[ch]["effects"]]
    b = fit_blocks(tr.t, clean_signal, true_cols, valid)
    r_true = ph.std100(tr.t, clean_signal - predict(b, true_cols), valid=valid)

    fams = []
    for e in added:
        kind = e.get("kind")
        params = e.get("params", {})
        if kind not in ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "time_drift",
                        "warmup"):
            return False, float("nan"), floor
        fams.append((kind, params))

    # coordinate search over each family's tau (coarse grid then refine), others held
    taus = [float(p.get("tau_s", 1000.0)) if k in NEEDS_TAU else None for k, p in fams]
    win = [120.0] * len(fams)

    def resid(taus_, win_=None):
        win_ = win if win_ is None else win_
        cols = list(decl)
        for (k, p), tau, w in zip(fams, taus_, win_):
            cc = _lib_columns(tr, k, p, own, case.dt, tau, w)
            if cc is None:
                return np.inf
            cols += cc
        bb = fit_blocks(tr.t, clean_signal, cols, valid)
        return ph.std100(tr.t, clean_signal - predict(bb, cols), valid=valid)

    best = resid(taus)
    for _ in range(2):
        for i, (k, p) in enumerate(fams):
            if k in ("rate", "rate_squared", "temp_rate_cross"):
                for w in (20.0, 60.0, 120.0, 240.0, 480.0, 900.0):
                    ww = list(win)
                    ww[i] = w
                    r = resid(taus, ww)
                    if r < best:
                        best, win = r, ww
            if k not in NEEDS_TAU:
                continue
            grid = TAUS if k == "thermal_lag" else np.geomspace(60, 6000, 40)
            for tau in grid[::3]:
                tt = list(taus)
                tt[i] = float(tau)
                r = resid(tt)
                if r < best:
                    best, taus = r, tt
            for f in np.geomspace(0.8, 1.25, 9):
                tt = list(taus)
                tt[i] = taus[i] * f
                r = resid(tt)
                if r < best:
                    best, taus = r, tt
    excess = float(np.sqrt(max(best ** 2 - r_true ** 2, 0.0)))
    return excess <= 0.5 * floor, excess, floor

"""The referee's own numbers from the recorded data: "before" (the declared model alone) and the
oracle (declared terms plus the true effects in their true form and true parameters), both fitted by
least squares on every training sample where the gyro was measured, both scored as the std of the
validation run's 100-s means over the blocks whose declared inputs stay inside the training range.

Recorded temperatures are linearly interpolated over failed conversions; rates are 120-s centred
least-squares slopes; power-on instants are the rising edges of the ``power`` column.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tests.referee4.cases import (Case, block_index, block_means, declared_inputs,
                                  declared_regressors)
from tests.referee4.effects import RATE_WINDOW_S, Signals, centred_slope, regressor

BLOCK_S = 100.0


def recorded_signals(cols: dict[str, np.ndarray], *, interpolate: bool) -> Signals:
    """Temperatures and rates as recorded.  ``interpolate=False`` (the declared model, as the product
    reads it): a failed conversion stays missing and rates are slopes over the present readings only;
    ``interpolate=True`` (the oracle's true effects): temperatures interpolated over the failures."""
    t = cols["time_s"]
    near_outage = _near_outage(t, RATE_WINDOW_S / 2)
    temps, rates = {}, {}
    for name, v in cols.items():
        if not name.startswith("temp_"):
            continue
        ok = np.isfinite(v)
        if interpolate:
            x = np.interp(t, t[ok], v[ok])
            temps[name[5:]], rates[name[5:]] = x, centred_slope(t, x)
        else:
            r = np.full(t.size, np.nan)
            r[ok] = centred_slope(t[ok], v[ok])
            r[near_outage] = np.nan
            temps[name[5:]], rates[name[5:]] = v, r
    p = cols["power"]
    edges = np.flatnonzero((p[1:] > 0.5) & (p[:-1] < 0.5)) + 1
    ons = [float(t[i]) for i in edges]
    if p[0] > 0.5:
        ons.insert(0, float(t[0]))
    return Signals(t=t, temps=temps, rates=rates, power_on_s=ons)


def _near_outage(t: np.ndarray, half_window_s: float) -> np.ndarray:
    """Rows less than half a rate window minus one sample period from a logger outage (a time step
    over 1.5 sample periods): the product's rate is undefined there (its fit skips them, its
    in-range test fails them; the exact reach was matched on this referee's cases)."""
    dt = float(np.median(np.diff(t)))
    near = np.zeros(t.size, dtype=bool)
    for i in np.flatnonzero(np.diff(t) > 1.5 * dt):
        reach = half_window_s - dt
        near |= ((t <= t[i]) & (t > t[i] - reach)) | ((t >= t[i + 1]) & (t < t[i + 1] + reach))
    return near


@dataclass
class ChannelScore:
    before_std100: float
    oracle_std100: float
    in_range_blocks: int
    blocks: int


def _design(case: Case, ch: str, cols: dict, with_truth: bool) -> np.ndarray:
    tr = case.truth[ch]
    decl = recorded_signals(cols, interpolate=False)
    parts = [np.ones(decl.t.size), declared_regressors(case.model, decl, tr["probe"])]
    if with_truth:
        sig = recorded_signals(cols, interpolate=True)
        for e in tr["effects"]:
            parts.append(regressor(e["kind"], e["params"], sig)[:, None])
    return np.column_stack(parts)


def _in_range_rows(case: Case, ch: str, sig_t: Signals, sig_v: Signals, rows_train: np.ndarray,
                   measured: np.ndarray) -> np.ndarray:
    """Measured validation rows that count as in range: the range test runs on 100-s blocks counted
    from the run's first row; a block in which any measured row with every declared input present has
    an input outside its training range is dropped whole (a row with a missing input, a failed
    conversion, enters no mean and drops nothing)."""
    probe = case.truth[ch]["probe"]
    ins_t = declared_inputs(case.model, sig_t, probe)
    ins_v = declared_inputs(case.model, sig_v, probe)
    ok = np.ones(sig_v.t.size, dtype=bool)
    for k in ins_t:
        lo, hi = np.min(ins_t[k][rows_train]), np.max(ins_t[k][rows_train])
        ok &= (ins_v[k] >= lo) & (ins_v[k] <= hi)
    grid = block_index(sig_v.t, sig_v.t[0], BLOCK_S)
    present = np.ones(sig_v.t.size, dtype=bool)
    for k in ins_v:
        present &= np.isfinite(ins_v[k])
    bad = np.unique(grid[measured & present & ~ok])
    return measured & ~np.isin(grid, bad)


def channel_score(case: Case, ch: str) -> ChannelScore:
    """Before and oracle on the validation run: std (ddof 1) of the 100-s means over the in-range
    rows, blocks counted from the run's first row, only blocks holding at least half their usual
    number of samples (the median per block)."""
    ct, cv = case.columns["train"], case.columns["validate"]
    sig_t = recorded_signals(ct, interpolate=False)
    sig_v = recorded_signals(cv, interpolate=False)
    yt, yv = ct[f"gyro_{ch}"], cv[f"gyro_{ch}"]
    tv = cv["time_s"]
    measured = np.isfinite(yv)
    out = {}
    for label, truth in (("before", False), ("oracle", True)):
        xt, xv = _design(case, ch, ct, truth), _design(case, ch, cv, truth)
        rt = np.isfinite(yt) & np.all(np.isfinite(xt), axis=1)
        use = _in_range_rows(case, ch, sig_t, sig_v, rt, measured) & np.all(np.isfinite(xv), axis=1)
        if not use.any():
            out[label], out["n"] = float("nan"), (0, 0)
            continue
        idx = block_index(tv, tv[0], BLOCK_S)
        scale = np.max(np.abs(xt[rt]), axis=0)
        scale[scale == 0] = 1.0
        coef, *_ = np.linalg.lstsq(xt[rt] / scale, yt[rt], rcond=None)
        res = yv[use] - (xv[use] / scale) @ coef
        blocks, means = block_means(idx[use], res)
        counts = np.array([np.sum(idx[use] == b) for b in blocks])
        sel = counts >= 0.5 * float(np.median(np.bincount(idx)[np.bincount(idx) > 0]))
        out[label] = float(np.std(means[sel, 0], ddof=1)) if sel.sum() > 2 else float("nan")
        out["n"] = (int(sel.sum()), int(np.unique(block_index(tv[measured], tv[measured][0], BLOCK_S)).size))
    return ChannelScore(before_std100=out["before"], oracle_std100=out["oracle"],
                        in_range_blocks=out["n"][0], blocks=out["n"][1])

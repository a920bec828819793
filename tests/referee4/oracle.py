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
from tests.referee4.effects import Signals, centred_slope, regressor

BLOCK_S = 100.0


def recorded_signals(cols: dict[str, np.ndarray], *, interpolate: bool) -> Signals:
    """Temperatures and rates as recorded.  ``interpolate=False`` (the declared model, as the product
    reads it): a failed conversion stays missing and rates are slopes over the present readings only;
    ``interpolate=True`` (the oracle's true effects): temperatures interpolated over the failures."""
    t = cols["time_s"]
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
            temps[name[5:]], rates[name[5:]] = v, r
    p = cols["power"]
    edges = np.flatnonzero((p[1:] > 0.5) & (p[:-1] < 0.5)) + 1
    ons = [float(t[i]) for i in edges]
    if p[0] > 0.5:
        ons.insert(0, float(t[0]))
    return Signals(t=t, temps=temps, rates=rates, power_on_s=ons)


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


def _in_range_blocks(case: Case, ch: str, sig_t: Signals, sig_v: Signals,
                     idx: np.ndarray, rows_train: np.ndarray, rows_val: np.ndarray) -> set[int]:
    """Blocks whose every measured row has its declared inputs recorded (a failed conversion is not
    in range: the product drops the block for one missing probe reading) and inside their training
    range."""
    probe = case.truth[ch]["probe"]
    ins_t = declared_inputs(case.model, sig_t, probe)
    ins_v = declared_inputs(case.model, sig_v, probe)
    ok = np.ones(rows_val.sum(), dtype=bool)
    for k in ins_t:
        lo, hi = np.min(ins_t[k][rows_train]), np.max(ins_t[k][rows_train])
        v = ins_v[k][rows_val]
        ok &= (v >= lo) & (v <= hi)
    bad = set(np.unique(idx[~ok]).tolist())
    return set(np.unique(idx).tolist()) - bad


def channel_score(case: Case, ch: str) -> ChannelScore:
    ct, cv = case.columns["train"], case.columns["validate"]
    sig_t = recorded_signals(ct, interpolate=False)
    sig_v = recorded_signals(cv, interpolate=False)
    yt, yv = ct[f"gyro_{ch}"], cv[f"gyro_{ch}"]
    out = {}
    for label, truth in (("before", False), ("oracle", True)):
        xt, xv = _design(case, ch, ct, truth), _design(case, ch, cv, truth)
        rt = np.isfinite(yt) & np.all(np.isfinite(xt), axis=1)
        rv = np.isfinite(yv) & np.all(np.isfinite(xv), axis=1)
        gv = np.isfinite(yv)
        idx = block_index(cv["time_s"][gv], cv["time_s"][gv][0], BLOCK_S)   # from the first measured sample
        good = _in_range_blocks(case, ch, sig_t, sig_v, idx, rt, gv)
        scale = np.max(np.abs(xt[rt]), axis=0)
        scale[scale == 0] = 1.0
        coef, *_ = np.linalg.lstsq(xt[rt] / scale, yt[rt], rcond=None)
        res = np.where(rv, yv - (np.nan_to_num(xv) / scale) @ coef, np.nan)[gv]
        blocks, means = block_means(idx, res)
        sel = np.isin(blocks, list(good))
        out[label] = float(np.std(means[sel, 0], ddof=1)) if sel.sum() > 2 else float("nan")
        out["n"] = (int(sel.sum()), int(np.unique(idx).size))
    return ChannelScore(before_std100=out["before"], oracle_std100=out["oracle"],
                        in_range_blocks=out["n"][0], blocks=out["n"][1])

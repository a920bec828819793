"""The referee's own numbers: declared-model "before" and the true-form "oracle".

Both are ordinary least squares on TRAIN (every row where the gyro was measured), predicted on
VALIDATE and scored as the std (ddof=1) of 100-s means of the validation residual.  Blocks are
counted from the validation run's first row; a block is kept when it holds at least half of its
nominal samples and every declared input of every row in it (raw readings; a failed reading is
ignored) lies inside the input's TRAIN range.

Declared regressors are evaluated on the recorded data: a probe temperature is the reading with
failed readings linearly interpolated, powers are of (T - 20)/30, and a derivative ``dX`` is the
centred least-squares slope over ``SLOPE_WINDOW_S`` seconds in C/min.  The oracle adds, to the
declared regressors, every true library effect in its true form with its true nonlinear parameters
(tau, width, threshold, T0, power-on time) evaluated on the same recorded data (Effect.regressor);
its amplitude is refitted like any coefficient.  Lag and memory states start at rest / neutral on
the first recorded row, as any analysis of the file must.
"""
from __future__ import annotations

import re

import numpy as np

from . import physics as ph

SLOPE_WINDOW_S = 120.0
RANGE_INCLUDES_RATES = True     # a declared rate is an input too: its TRAIN range counts

_TERM = re.compile(r"^(?:(?P<d>d)?(?P<p>tc|t\d)(?:\^(?P<k>\d))?|\((?P<a>tc|t\d)-(?P<b>tc|t\d)\))$")


def centred_mean(t, x, window_s):
    lo = np.searchsorted(t, t - window_s / 2, side="left")
    hi = np.searchsorted(t, t + window_s / 2, side="right")
    c = np.concatenate([[0.0], np.cumsum(x)])
    return (c[hi] - c[lo]) / (hi - lo)


def parse_model(model: str):
    terms = []
    for raw in model.split(" + "):
        m = _TERM.match(raw.strip())
        if not m:
            raise ValueError(f"unsupported term {raw!r}")
        if m.group("a"):
            terms.append(("diff", m.group("a"), m.group("b")))
        elif m.group("d"):
            terms.append(("rate", m.group("p")))
        else:
            terms.append(("pow", m.group("p"), int(m.group("k") or 1)))
    return terms


def declared(rec: dict, model: str, own: str):
    """(design matrix without intercept, list of raw input arrays for the range test)."""
    t = rec["t"]

    def name(p):
        return own if p == "tc" else p

    cols, inputs, seen = [], [], set()
    for term in parse_model(model):
        if term[0] == "pow":
            p = name(term[1])
            cols.append(((rec["probes_i"][p] - 20.0) / 30.0) ** term[2])
            if p not in seen:
                inputs.append(rec["probes"][p])
                seen.add(p)
        elif term[0] == "diff":
            a, b = name(term[1]), name(term[2])
            cols.append(rec["probes_i"][a] - rec["probes_i"][b])
            key = f"{a}-{b}"
            if key not in seen:
                inputs.append(rec["probes"][a] - rec["probes"][b])
                seen.add(key)
        else:
            p = name(term[1])
            r = ph.local_slope(t, rec["probes_i"][p], SLOPE_WINDOW_S)
            cols.append(r)
            if RANGE_INCLUDES_RATES:
                inputs.append(r)
    return np.column_stack(cols), inputs


def in_range_mask(val_inputs, train_inputs, train_present):
    """Row mask: every declared input inside its TRAIN range (NaN readings do not count)."""
    ok = np.ones(len(val_inputs[0]), bool)
    for v, tr in zip(val_inputs, train_inputs):
        x = tr[train_present & np.isfinite(tr)]
        lo, hi = x.min(), x.max()
        ok &= ~np.isfinite(v) | ((v >= lo) & (v <= hi))
    return ok


def blocks_in_range(rec, row_ok):
    t = rec["t"]
    b = np.floor((t - t[0]) / 100.0).astype(int)
    bad = np.bincount(b[~row_ok], minlength=b.max() + 1) > 0
    return bad


def scored_std100(rec, resid, row_ok):
    """std of 100-s means over in-range blocks, and the coverage (share of blocks kept)."""
    idx, means, _ = ph.block_means(rec["t"], resid, rec["t"][0], period_s=rec["period"])
    bad = blocks_in_range(rec, row_ok)
    keep = ~bad[idx]
    if keep.sum() < 2:
        return float("nan"), 0.0
    return float(np.std(means[keep], ddof=1)), float(keep.mean())


def run_std100(rec, y):
    return ph.std100(rec["t"], y, rec["t"][0], rec["period"])


def _fit_predict(Xtr, ytr, Xva):
    A = np.column_stack([np.ones(len(Xtr)), Xtr])
    B = np.column_stack([np.ones(len(Xva)), Xva])
    beta, *_ = np.linalg.lstsq(A, ytr, rcond=None)
    return A @ beta, B @ beta


def fit_score(train, val, own, model, ytr, yva, extra_tr=(), extra_va=(), present_tr=None,
              present_va=None):
    """Fit declared (+extra) on TRAIN rows with finite y; std100 of the validation residual."""
    Xtr, in_tr = declared(train, model, own)
    Xva, in_va = declared(val, model, own)
    if len(extra_tr):
        Xtr = np.column_stack([Xtr] + list(extra_tr))
        Xva = np.column_stack([Xva] + list(extra_va))
    ptr = np.isfinite(ytr) if present_tr is None else present_tr & np.isfinite(ytr)
    pva = np.isfinite(yva) if present_va is None else present_va & np.isfinite(yva)
    fit_tr, pred_va = _fit_predict(Xtr[ptr], ytr[ptr], Xva)
    res_tr = np.full(len(ytr), np.nan)
    res_tr[ptr] = ytr[ptr] - fit_tr
    res_va = np.where(pva, yva - pred_va, np.nan)
    ok = in_range_mask(in_va, in_tr, ptr)
    s_va, cov = scored_std100(val, res_va, ok)
    s_tr = run_std100(train, res_tr)
    return dict(train=s_tr, val=s_va, coverage=cov, res_va=res_va)


def unabsorbed(train, val, own, model, sig_tr, sig_va, present_tr, present_va):
    """What the declared model fitted on TRAIN leaves of a noise-free signal: std100 on TRAIN and
    on the in-range VALIDATE blocks."""
    r = fit_score(train, val, own, model, np.where(present_tr, sig_tr, np.nan),
                  np.where(present_va, sig_va, np.nan))
    return r["train"], r["val"]


def channel_numbers(case, ch):
    """Referee 'before' (declared only) and 'oracle' (declared + true effects) for a channel."""
    own = case.channel_probes[ch]
    ytr, yva = case.train["gyro"][ch], case.val["gyro"][ch]
    before = fit_score(case.train, case.val, own, case.model, ytr, yva)
    effs = [e for e in case.truth[ch].effects if e.library]
    if effs:
        etr = [e.regressor(case.train) for e in effs]
        eva = [e.regressor(case.val) for e in effs]
        oracle = fit_score(case.train, case.val, own, case.model, ytr, yva, etr, eva)
    else:
        oracle = before
    # the realised noise alone over the same in-range blocks: what a perfect model would leave
    s_noise, _ = scored_std100(case.val, case.val["noise"][ch], _in_range_rows(case, ch))
    return dict(before=before["val"], oracle=oracle["val"], coverage=before["coverage"],
                before_train=before["train"], oracle_train=oracle["train"], noise_inrange=s_noise)


def _in_range_rows(case, ch):
    own = case.channel_probes[ch]
    _, in_tr = declared(case.train, case.model, own)
    _, in_va = declared(case.val, case.model, own)
    return in_range_mask(in_va, in_tr, np.isfinite(case.train["gyro"][ch]))


def coverage(case, ch) -> float:
    """Share of the validation run's 100-s blocks inside every declared input's TRAIN range."""
    ok = _in_range_rows(case, ch)
    idx, _, _ = ph.block_means(case.val["t"], case.val["gyro"][ch], case.val["t"][0],
                               period_s=case.val["period"])
    if len(idx) == 0:
        return 0.0
    bad = blocks_in_range(case.val, ok)
    return float((~bad[idx]).mean())

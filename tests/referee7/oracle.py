"""Referee 7 oracle: what a fitter that knew the true effect columns would reach on VALIDATE.

Conventions:

* std100 = sample std (ddof=1) of 100-s block means; blocks are ``floor(t/100)`` of the true row instant
  (s since run start); a block counts when it holds at least half its nominal samples.
* In range = VALIDATE rows whose declared inputs (logged own probe, t4 for ``(tc-t4)``, true rate for
  ``dtc``) lie inside TRAIN's range of the same inputs.
* Oracle = least squares on TRAIN of [1, declared terms, true effect columns] (all true, noise-free
  physical quantities mapped onto the logged rows), residual std100 on in-range VALIDATE.
* Also returned: ``declared`` (same without effect columns) and ``noise`` (gyro minus true bias).
"""
from __future__ import annotations

import numpy as np

from .cases import OWN, column, declared_columns


def std100(t: np.ndarray, r: np.ndarray, period: float) -> float:
    ok = np.isfinite(r)
    t, r = t[ok], r[ok]
    blk = np.floor(t / 100.0).astype(int)
    blk -= blk.min()
    cnt = np.bincount(blk)
    sm = np.bincount(blk, weights=r)
    good = cnt >= 0.5 * 100.0 / period
    means = sm[good] / cnt[good]
    return float(np.std(means, ddof=1)) if len(means) > 2 else float("nan")


def _inputs(case, which, ch):
    rr = case["runs"][which]
    own = OWN[ch]
    out = []
    logged = rr["cols"][f"temp_{own}"]
    out.append(np.where(np.isfinite(logged), logged, rr["rows"].at(rr["run"]["T"][own])))
    if "(tc-t4)" in case["formula"]:
        l4 = rr["cols"]["temp_t4"]
        out.append(np.where(np.isfinite(l4), l4, rr["rows"].at(rr["run"]["T"]["t4"])))
    if "dtc" in case["formula"]:
        out.append(rr["rows"].at(rr["run"]["rate"][own]))
    return out


def in_range_mask(case, ch) -> np.ndarray:
    mask = None
    for a, b in zip(_inputs(case, "train", ch), _inputs(case, "validate", ch)):
        m = (b >= np.nanmin(a)) & (b <= np.nanmax(a))
        mask = m if mask is None else mask & m
    return mask


def _design(case, which, ch, with_effects, effects=None):
    rr = case["runs"][which]
    run, rows = rr["run"], rr["rows"]
    cols = [np.ones(len(rows.t))]
    cols += [rows.at(c) for c in declared_columns(case["formula"], run, OWN[ch])]
    if with_effects:
        effects = case["truth"][ch]["effects"] if effects is None else effects
        cols += [rows.at(column(run, nm, pr, par)) for nm, pr, par in effects]
    return np.column_stack(cols)


def _fit_val(case, ch, effects):
    """(train rms, validation std100) of the declared model plus ``effects`` (true columns)."""
    tr, va = case["runs"]["train"], case["runs"]["validate"]
    y_tr, y_va = tr["cols"][f"gyro_{ch}"], va["cols"][f"gyro_{ch}"]
    mask = in_range_mask(case, ch) & np.isfinite(y_va)
    X, Xv = _design(case, "train", ch, True, effects), _design(case, "validate", ch, True, effects)
    ok = np.isfinite(y_tr)
    beta, res = np.linalg.lstsq(X[ok], y_tr[ok], rcond=None)[:2]
    r = np.where(mask, y_va - Xv @ beta, np.nan)
    return float(np.sum((y_tr[ok] - X[ok] @ beta) ** 2)), std100(va["rows"].t, r, va["rows"].period)


GRIDS = {"lag": list(np.geomspace(100, 8000, 16)), "lag_rel": list(np.geomspace(100, 8000, 16)), "relay": [0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0],
         "gradual": [0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0], "warmup": [200, 350, 600, 1000, 1700, 3000]}


def tuned(case, ch, named) -> float:
    """Validation std100 of the declared model plus the effects ``named`` [(name, probe)], true physics
    columns, each parameter (lag tau, hysteresis width, warm-up tau) chosen on TRAIN by coordinate
    search over a grid: what an ideal fitter naming exactly these effects would reach."""
    eff = [(nm, pr, GRIDS[nm][len(GRIDS[nm]) // 2] if nm in GRIDS else None) for nm, pr in named]
    best = _fit_val(case, ch, eff)
    for _ in range(2):
        for i, (nm, pr, _) in enumerate(eff):
            for par in GRIDS.get(nm, []):
                trial = list(eff)
                trial[i] = (nm, pr, par)
                got = _fit_val(case, ch, trial)
                if got[0] < best[0]:
                    best, eff = got, trial
    for i, (nm, pr, par) in enumerate(eff):          # refine continuous time constants
        if nm in ("lag", "lag_rel", "warmup"):
            for f in np.concatenate([np.linspace(0.75, 1.33, 15), np.linspace(0.95, 1.05, 11)]):
                trial = list(eff)
                trial[i] = (nm, pr, eff[i][2] * f)
                got = _fit_val(case, ch, trial)
                if got[0] < best[0]:
                    best, eff = got, trial
    return best[1]


def evaluate(case, ch) -> dict:
    tr, va = case["runs"]["train"], case["runs"]["validate"]
    y_tr, y_va = tr["cols"][f"gyro_{ch}"], va["cols"][f"gyro_{ch}"]
    mask = in_range_mask(case, ch) & np.isfinite(y_va)
    out = {"coverage": float(mask.mean())}
    for key, eff in (("oracle", True), ("declared", False)):
        X, Xv = _design(case, "train", ch, eff), _design(case, "validate", ch, eff)
        ok = np.isfinite(y_tr)
        beta = np.linalg.lstsq(X[ok], y_tr[ok], rcond=None)[0]
        r = np.where(mask, y_va - Xv @ beta, np.nan)
        out[key] = std100(va["rows"].t, r, va["rows"].period)
    noise = np.where(mask, y_va - va["gyro_truth"][ch], np.nan)
    out["noise"] = std100(va["rows"].t, noise, va["rows"].period)
    return out

"""Where a fitted model is valid on new data, and its error there (range-aware validation).

A model fitted on a training run is only known inside the range its inputs covered there (the
``validity["signals"]`` box of a linear FitResult: signal key -> [lo, hi]).  A validation run that
leaves that range (colder, hotter, steeper ramps) is split in two:

* the **in-range** part: every declared input inside its training range.  There the deployed model
  (inputs clipped to the range) and the fitted equation are the same thing, so its error is the
  model's own error.  ``validation_std100_dph`` (over the 100-s blocks wholly in range) and
  ``validation_rms_dph`` (over the in-range samples) are measured there;
* the rest, where the deployed model clips its inputs.  ``validation_all_std100_dph`` is the whole
  run with the model as deployed (clipped); ``validation_coverage`` the in-range fraction.

Pure functions over arrays.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from bench.fit.metrics import bias_stability


def in_range_mask(signals: Mapping[str, np.ndarray], ranges: Mapping[str, list[float]], n: int) -> np.ndarray:
    """True where every signal that has a training range lies inside it (NaN counts as outside)."""
    mask = np.ones(n, dtype=bool)
    for key, (lo, hi) in ranges.items():
        if key in signals:
            v = np.asarray(signals[key], dtype=np.float64)
            with np.errstate(invalid="ignore"):
                mask &= (v >= lo) & (v <= hi)
    return mask


def outside_summary(signals: Mapping[str, np.ndarray], ranges: Mapping[str, list[float]],
                    usable: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
    """Per declared input: its training range, its range on the new data and the fractions of the
    (usable) new samples below and above the training range; only inputs that leave it are listed."""
    out: dict[str, dict[str, Any]] = {}
    for key, (lo, hi) in ranges.items():
        if key not in signals:
            continue
        v = np.asarray(signals[key], dtype=np.float64)
        ok = np.isfinite(v) if usable is None else (usable & np.isfinite(v))
        if not ok.any():
            continue
        below, above = float(np.mean(v[ok] < lo)), float(np.mean(v[ok] > hi))
        if below > 0 or above > 0:
            out[key] = {"train_range": [float(lo), float(hi)],
                        "validation_range": [float(np.min(v[ok])), float(np.max(v[ok]))],
                        "fraction_below": below, "fraction_above": above}
    return out


def whole_blocks(mask: np.ndarray, time_s: np.ndarray, block_s: float = 100.0,
                 usable: np.ndarray | None = None) -> np.ndarray:
    """``mask`` reduced to the ``block_s`` blocks (counted from the run's first row, the grid of every
    std of 100-s means, ``bench.fit.metrics.window_means``) in which every usable sample lies inside
    it: a block mean is in range only if every sample that enters it is.  A sample that enters no
    mean (``usable`` False: a failed probe conversion, a missing gyro value) does not take its block
    out of range."""
    t = np.asarray(time_s, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if len(t) == 0:
        return m
    counts = np.ones(len(t), dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    block = np.floor((t - t[0]) / float(block_s)).astype(np.int64)
    outside = np.bincount(block, (counts & ~m).astype(np.int64))
    return (outside == 0)[block] & m


def range_aware_errors(residual: np.ndarray, deployed_residual: np.ndarray, time_s: np.ndarray,
                       in_range: np.ndarray) -> dict[str, float]:
    """The four validation numbers: std of 100-s means and RMS on the in-range part, the in-range
    fraction of the usable samples, and the std of 100-s means of the deployed (clipped) model on the
    whole run.  ``residual`` may be the unclipped or the deployed residual: they agree in range."""
    r = np.asarray(residual, dtype=np.float64)
    usable = np.isfinite(r)
    inside = usable & in_range
    r_in = np.where(whole_blocks(in_range, time_s, usable=usable) & usable, r, np.nan)
    n_usable = int(usable.sum())
    return {
        "validation_std100_dph": bias_stability(time_s, r_in, 100.0),
        "validation_rms_dph": float(np.sqrt(np.mean(r[inside] ** 2))) if inside.any() else float("nan"),
        "validation_coverage": float(inside.sum() / n_usable) if n_usable else 0.0,
        "validation_all_std100_dph": bias_stability(time_s, np.asarray(deployed_residual, np.float64), 100.0),
    }


def result_in_range(result: Any, data: Any, flagged: np.ndarray) -> np.ndarray:
    """In-range mask of a FitResult on ``data``: the box of its declared inputs for models linear in
    their coefficients (the convex (T, dT/dt) hull is a deployment guard, not part of the range);
    for the other models, where their own predict did not flag the sample."""
    d = result.definition
    ranges = result.validity.get("signals") if isinstance(result.validity, dict) else None
    if d.get("kind") == "linear" and ranges:
        from bench.fit.formula import compiled_from_recipe

        compiled = compiled_from_recipe(d["terms"], d.get("formula", ""), d["rate_filter"]["window_s"],
                                        d.get("target_unit", "deg/h"))
        return in_range_mask(compiled.signals(data), ranges, len(data))
    return ~np.asarray(flagged, dtype=bool)

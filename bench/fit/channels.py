"""Fit one model on every channel and score it on the training and validation data: the document the
``bench fit`` command prints and ``POST /fits`` stores.  Pure: datasets in, JSON-able dict out."""
from __future__ import annotations

from typing import Any

import numpy as np

from bench.fit.base import Dataset, FitResult
from bench.fit.catalog import fit_model, predict, target_of
from bench.fit.metrics import bias_stability
from bench.fit.prep import screen_glitches
from bench.fit.validity import range_aware_errors, result_in_range
from bench.jsonsafe import jsonable


def prediction_metrics(values: np.ndarray, target: np.ndarray, time_s: np.ndarray,
                       flagged: np.ndarray) -> dict[str, Any]:
    """RMS (deg/h) and std of 100-s means (deg/h) of target - values, sample count, flagged fraction."""
    resid = np.asarray(target, float) - np.asarray(values, float)
    ok = np.isfinite(resid)
    return {"rms_dph": float(np.sqrt(np.mean(resid[ok] ** 2))) if ok.any() else None,
            "std100_dph": bias_stability(time_s, np.where(ok, resid, np.nan), 100.0),
            "n": int(ok.sum()), "flagged_fraction": float(np.mean(flagged)) if len(flagged) else 0.0}


def validation_errors(result: FitResult, data: Dataset, values: np.ndarray, target: np.ndarray,
                      flagged: np.ndarray) -> dict[str, Any]:
    """Range-aware validation numbers (``bench.fit.validity``): in-range std100/RMS, coverage, and the
    deployed model's std100 on the whole run."""
    resid = np.asarray(target, float) - np.asarray(values, float)
    return range_aware_errors(resid, resid, data.time, result_in_range(result, data, flagged))


def fit_channels(model: str, train: Dataset, validate: Dataset | None, channels: list[str],
                 opts: dict[str, Any]) -> tuple[dict, list[FitResult]]:
    """Fit ``model`` per channel; returns the JSON document (strict JSON) and the FitResults."""
    # an isolated glitch (a corrupted frame, a probe's power-on reading) is a missing reading, not data
    train, glitches_train = screen_glitches(train)
    glitches: dict[str, Any] = {"training": glitches_train}
    if validate is not None:
        validate, glitches["validation"] = screen_glitches(validate)
    doc: dict[str, Any] = {"model": model, "glitches_removed": glitches, "channels": {}}
    results = []
    for ch in channels:
        result = fit_model(model, train, ch, **opts)
        results.append(result)
        entry: dict[str, Any] = {"model": result.model, "coefficients": result.coefficients, "units": result.units,
                                 "validity": result.validity, "definition": result.definition,
                                 "stats": result.stats}
        for label, data in (("train", train), ("validation", validate)):
            if data is None:
                continue
            values, flagged = predict(result, data)
            target = target_of(result, data)
            entry[label] = prediction_metrics(values, target, data.time, flagged)
            if label == "validation":
                entry[label].update(validation_errors(result, data, values, target, flagged))
            if result.model == "hrg_reverse":
                err = np.abs(np.asarray(values) - target)
                entry[label]["max_abs_error_c"] = float(np.nanmax(err))
        if result.model == "hrg_reverse":
            entry["max_abs_error_c"] = entry["train"]["max_abs_error_c"]
        doc["channels"][ch] = entry
    return jsonable(doc), results

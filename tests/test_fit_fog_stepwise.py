"""FOG stepwise regression (seed 004 eq 6) on synthetic start-up runs.

Synthetic physics: the gyro is switched on at eight soak temperatures (paper: -40...60 C); self-heating
raises its temperature by ~12 C with a ~20 min first-order time constant, so dT/dt is large at
start-up and decays.  The bias is a known function of a few eq-6 terms plus AR(1) noise (correlated
over ~16 min at 100-s resolution: rho = 0.9 per 100 s), sampled every 10 s for 2 h per run.
"""
from __future__ import annotations

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.fog import fit_fog_stepwise, predict_fog_stepwise

T0 = 10.0
TRUE_TERMS = {"T", "T^2", "dT", "T*dT"}
TRUE_COEF = {"Y0": 0.5, "T": 0.01, "T^2": 1.1e-4, "dT": 0.8, "T*dT": 0.02}   # deg/h per C^p (C/min)^q


def startup_runs(seed: int, rho_100s: float = 0.9, sd: float = 0.01, dt: float = 10.0,
                 starts=(-40, -25, -10, 5, 20, 35, 45, 60)) -> Dataset:
    rng = np.random.default_rng(seed)
    t_run = np.arange(0.0, 7200.0, dt)
    rho = rho_100s ** (dt / 100.0)
    cols = {"time_s": [], "temp_t1": [], "gyro_x": [], "run": []}
    t_offset = 0.0
    for k, start in enumerate(starts):
        rise, tau_s = 12.0 + rng.normal(0, 1), (20.0 + rng.normal(0, 2)) * 60.0
        temp = start + rise * (1 - np.exp(-t_run / tau_s))
        rate = rise / tau_s * 60.0 * np.exp(-t_run / tau_s)          # C/min
        x = temp - T0
        bias = (TRUE_COEF["Y0"] + TRUE_COEF["T"] * x + TRUE_COEF["T^2"] * x ** 2 + TRUE_COEF["dT"] * rate
                + TRUE_COEF["T*dT"] * x * rate)
        # AR(1) noise; the 100-s means of this series have lag-1 correlation ~ rho_100s
        innov = rng.normal(0, sd * np.sqrt(1 - rho ** 2) * np.sqrt(10), t_run.size)
        noise = np.empty(t_run.size)
        noise[0] = rng.normal(0, sd * np.sqrt(10))
        for i in range(1, t_run.size):
            noise[i] = rho * noise[i - 1] + innov[i]
        cols["time_s"].append(t_offset + t_run)
        cols["temp_t1"].append(temp + rng.normal(0, 0.01, t_run.size))
        cols["gyro_x"].append(bias + noise)
        cols["run"].append(np.full(t_run.size, k))
        t_offset += 7200.0 + 3600.0
    return Dataset({k: np.concatenate(v).astype(float) for k, v in cols.items()})


def test_true_terms_recovered_and_junk_rejected_on_ar1_noise():
    """Decimated tests (default) find exactly the true set in most runs and let almost no junk in;
    plain OLS p-values on the same autocorrelated data accept several junk terms per run."""
    exact, junk, missed, ols_junk = 0, 0, 0, 0
    seeds = range(1, 7)
    for seed in seeds:
        data = startup_runs(seed)
        res = fit_fog_stepwise(data, "x", probe="t1", t0_c=T0)
        chosen = {t["name"] for t in res.definition["terms"]}
        exact += chosen == TRUE_TERMS
        junk += len(chosen - TRUE_TERMS)
        missed += len(TRUE_TERMS - chosen)
        assert res.definition["selection"]["block_points"] >= 8     # rho ~ 0.9 -> ~15-point blocks
        plain = fit_fog_stepwise(data, "x", probe="t1", t0_c=T0, test="ols", sidak=False)
        ols_junk += len({t["name"] for t in plain.definition["terms"]} - TRUE_TERMS)
    assert exact >= 4, (exact, junk, missed)
    assert junk <= 2, (exact, junk, missed)
    assert ols_junk >= 2 * len(seeds), ols_junk


def test_coefficients_and_prediction():
    data = startup_runs(3, rho_100s=0.5, sd=0.005)
    res = fit_fog_stepwise(data, "x", probe="t1", t0_c=T0)
    assert {t["name"] for t in res.definition["terms"]} == TRUE_TERMS
    for name, value in TRUE_COEF.items():
        assert res.coefficients[name] == pytest.approx(value, rel=0.05, abs=2e-3), name
    pred, flagged = predict_fog_stepwise(res, data)
    assert pred.shape == data["gyro_x"].shape and np.all(np.isfinite(pred))
    assert flagged.mean() < 0.05
    assert np.sqrt(np.mean((data["gyro_x"] - pred) ** 2)) < 0.05
    hot = data.with_columns(temp_t1=data["temp_t1"] + 40.0)
    _, flagged_hot = predict_fog_stepwise(res, hot)
    assert flagged_hot[data["temp_t1"] + 40.0 > res.validity["tmax_c"] + 0.5].all()


def test_bad_input_named():
    data = startup_runs(1)
    with pytest.raises(DataFormatError, match="temp_t9"):
        fit_fog_stepwise(data, "x", probe="t9")
    with pytest.raises(DataFormatError, match="gyro_q"):
        fit_fog_stepwise(data, "q", probe="t1")
    with pytest.raises(DataFormatError, match="test must be"):
        fit_fog_stepwise(data, "x", probe="t1", test="magic")

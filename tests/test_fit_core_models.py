"""Models on synthetic runs with known truth: recovery, noise floor, 37 terms, validity, registry."""
from __future__ import annotations

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit import models, prep
from bench.fit.base import Dataset, FitResult
from bench.fit.formula import FormulaError
from bench.fit.metrics import bias_stability, profile_correlation, weakly_correlated
from tests.test_fit_core_synth import CAL_PROFILE, DYNAMIC_TRUE, STATIC_TRUE, VAL_PROFILE, thermal_run


def _rel_err(fit: dict, truth: dict) -> dict:
    return {k: abs(fit[k] / v - 1.0) for k, v in truth.items()}


@pytest.fixture(scope="module")
def static_run():
    return thermal_run(CAL_PROFILE, truth="static", seed=11)


@pytest.fixture(scope="module")
def dynamic_run():
    return thermal_run(CAL_PROFILE, truth="dynamic", seed=12)


@pytest.mark.parametrize("bin_c", [0.5, None])
def test_static_cubic_recovers_true_coefficients(static_run, bin_c):
    ds, _ = static_run
    res = models.fit_model("static", ds, "x", probe="t1", bin_c=bin_c)
    assert max(_rel_err(res.coefficients, STATIC_TRUE).values()) < 0.05, res.coefficients
    assert res.definition["t0_c"] == 25.0 and res.units["A3"] == "deg/h/C^3"
    assert res.validity["tmin_c"] < -19 and res.validity["tmax_c"] > 59
    assert ("bins" in res.stats["weighting"]) == (bin_c is not None)
    assert res.stats["std100_dph"] < 0.0065 and res.stats["improvement_pct"] > 95


def test_dynamic_eq4_recovers_true_coefficients(dynamic_run):
    ds, _ = dynamic_run
    res = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"))
    assert set(res.coefficients) == {"B0", "k", "p", "q"}
    assert max(_rel_err(res.coefficients, DYNAMIC_TRUE).values()) < 0.05, res.coefficients
    assert res.units["q"] == "deg/h/(C/min)" and res.units["p"] == "deg/h/C"
    assert "hull" in res.validity and res.definition["equation"] == "S000 eq 4"


def test_static_model_misses_the_dynamic_effect(dynamic_run):
    ds, _ = dynamic_run
    static = models.fit_model("static", ds, "x", probe="t1", bin_c=None)
    dynamic = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"))
    assert static.stats["std100_dph"] > 3 * dynamic.stats["std100_dph"]


def test_dynamic_eq5_orders_and_power_on_reference():
    truth = {"B0": 0.2, "k1": 0.01, "k2": 4e-4, "p": 0.25, "q1": 0.14, "q2": 0.08}

    def bias(tt, rr):
        d = tt["t1"] - 25.0
        return (truth["B0"] + truth["k1"] * d + truth["k2"] * d ** 2 + truth["p"] * (tt["t1"] - tt["t2"])
                + truth["q1"] * rr["t1"] + truth["q2"] * rr["t1"] ** 2)

    ds, _ = thermal_run(CAL_PROFILE, truth=bias, seed=13)
    res = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"), l=2, m=1, n=2)
    assert set(res.coefficients) == {"B0", "k1", "k2", "p", "q1", "q2"}
    assert max(_rel_err(res.coefficients, truth).values()) < 0.05, res.coefficients
    assert res.definition["equation"] == "S000 eq 5"
    po = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"), t0_c="power_on", l=2, m=1, n=2)
    assert po.definition["t0_c"] == ds["temp_t1"][0]
    # same model space, other reference: identical predictions
    np.testing.assert_allclose(models.predict(po, ds)[0], models.predict(res, ds)[0], atol=1e-6)


def test_formula_with_true_terms_reaches_the_noise_floor_on_a_validation_run():
    def bias(tt, rr):
        d = tt["t1"] - 25.0
        return 0.1 + 0.012 * d + 3e-4 * d ** 2 + 0.2 * (tt["t1"] - tt["t3"]) + 0.15 * rr["t1"] + 0.004 * d * rr["t1"]

    cal, _ = thermal_run(CAL_PROFILE, truth=bias, seed=21)
    val, val_truth = thermal_run(VAL_PROFILE, truth=bias, seed=22)
    formula = "(t1-25) + (t1-25)^2 + (t1-t3) + dt1 + (t1-25)*dt1"
    res = models.fit_model(formula, cal, "x")
    assert res.model == "formula" and "(t1-25)*dt1" in res.coefficients
    pred, flagged = models.predict(res, val)
    resid = val["gyro_x"] - pred
    floor = bias_stability(val.time, val_truth["noise"])
    got = bias_stability(val.time, resid)
    assert got <= 1.10 * floor, (got, floor)
    assert flagged.mean() < 0.05
    raw = bias_stability(val.time, val["gyro_x"])
    assert raw > 20 * got
    r = profile_correlation(cal.time, cal["chamber_pv"], val.time, val["chamber_pv"])
    assert weakly_correlated(r), r          # S001: validate on a weakly correlated run


def test_patent37_fits_and_predicts_with_condition_number():
    def bias(tt, rr):
        return (0.05 + 0.01 * (tt["t1"] - 25) + 2e-4 * (tt["t2"] - 25) ** 2 + 0.12 * rr["t3"]
                + 0.003 * (tt["t4"] - 25) * rr["t4"] - 0.02 * rr["t1"] ** 2)

    cal, _ = thermal_run(CAL_PROFILE, truth=bias, seed=31)
    res = models.fit_model("patent37", cal, "x")
    assert list(res.coefficients) == [f"a{i}" for i in range(37)]
    assert res.stats["k"] == 37 and np.isfinite(res.stats["cond"]) and res.stats["cond"] > 1
    assert res.definition["probes"] == ["t1", "t2", "t3", "t4"]
    assert res.units["a9"] == "deg/h/((C*C/min)^3)" and res.units["a4"] == "deg/h/(C/min)"
    assert res.stats["rms_dph"] < 0.052
    val, val_truth = thermal_run(VAL_PROFILE, truth=bias, seed=32)
    pred, flagged = models.predict(res, val)
    resid = (val["gyro_x"] - pred)[~flagged]
    assert np.sqrt(np.mean((resid - val_truth["noise"][~flagged]) ** 2)) < 0.03
    with pytest.raises(DataFormatError, match="4 probes"):
        models.fit_model("patent37", cal, "x", probes=["t1", "t2"])


def test_predict_clips_and_flags_outside_the_validity_range(static_run):
    ds, _ = static_run
    res = models.fit_model("static", ds, "x", probe="t1")
    tmax = res.validity["tmax_c"]
    hot = Dataset({"time_s": np.arange(5.0), "gyro_x": np.zeros(5), "temp_t1": np.array([20, tmax, tmax + 5, tmax + 30, np.nan])})
    values, flagged = models.predict(res, hot)
    assert flagged.tolist() == [False, False, True, True, False]
    assert values[2] == values[3] == pytest.approx(values[1])     # clipped to TMAX, not extrapolated
    assert np.isnan(values[4])
    nan_values, _ = models.predict(res, hot, mode="nan")
    assert np.isnan(nan_values[2]) and np.isfinite(nan_values[0])
    comp, _ = models.compensate(res, hot)
    np.testing.assert_allclose(comp[:2], -values[:2])


def test_dynamic_flags_points_outside_the_t_rate_hull(dynamic_run):
    ds, _ = dynamic_run
    res = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"))
    t = np.arange(4000.0)
    # inside the temperature range but heating at 3 C/min at -15 C, never seen in the fit data
    fast = Dataset({"time_s": t, "gyro_x": np.zeros(4000), "temp_t1": np.clip(-15 + (t - 2000) * 3.0 / 60.0, -20, 60),
                    "temp_t2": np.full(4000, 0.0)})
    _, flagged = models.predict(res, fast)
    mid = slice(1900, 2100)
    assert flagged[mid].all()


def test_fit_removes_the_earth_rate_when_latitude_is_known(static_run):
    ds, _ = static_run
    n = len(ds)
    codes = np.array(["ENU", "WSU", "ESD", "NUE"])[(np.arange(n) // 3000) % 4]
    lat = 30.0
    er = prep.body_earth_rates(Dataset({"time_s": ds.time, "orientation": codes}, {"latitude_deg": str(lat)}))[:, 0]
    moved = ds.with_columns(gyro_x=ds["gyro_x"] + er, orientation=codes)
    moved.meta["latitude_deg"] = str(lat)
    res = models.fit_model("static", moved, "x", probe="t1")
    assert res.definition["earth_rate"]["earth_rate_removed"] is True
    assert max(_rel_err(res.coefficients, STATIC_TRUE).values()) < 0.05
    kept = models.fit_model("static", moved, "x", probe="t1", earth_rate=False)
    assert kept.stats["std100_dph"] > 5 * res.stats["std100_dph"]


def test_block_average_option_and_pauta(dynamic_run):
    ds, _ = dynamic_run
    spiky = ds.with_columns(gyro_x=ds["gyro_x"].copy())
    spiky.columns["gyro_x"][::997] += 50.0
    res = models.fit_model("dynamic", spiky, "x", probe="t1", grad=("t1", "t2"))
    assert res.stats["n_rejected"] >= len(ds) // 997
    assert max(_rel_err(res.coefficients, DYNAMIC_TRUE).values()) < 0.05
    avg = models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2"), average_s=100.0, pauta=False)
    assert avg.stats["n_fit_points"] < len(ds) / 90
    assert max(_rel_err(avg.coefficients, DYNAMIC_TRUE).values()) < 0.05


def test_registry_accepts_outside_models_and_reports_unknown_names(static_run):
    ds, _ = static_run

    def fit_mean(dataset, channel, **opts):
        m = float(np.nanmean(dataset[f"gyro_{channel}"]))
        return FitResult("const_test", channel, f"gyro_{channel}", {"kind": "const"}, {"c": m}, {"c": "deg/h"},
                         {"tmin_c": None, "tmax_c": None})

    def predict_mean(result, dataset, **opts):
        return np.full(len(dataset), result.coefficients["c"]), np.zeros(len(dataset), bool)

    models.register_model("const_test", fit_mean, predict_mean, description="test", replace=True)
    res = models.fit_model("const_test", ds, "x")
    values, flagged = models.predict(res, ds)
    assert values[0] == pytest.approx(np.nanmean(ds["gyro_x"])) and not flagged.any()
    with pytest.raises(ValueError, match="already registered"):
        models.register_model("const_test", fit_mean, predict_mean)
    assert {"static", "dynamic", "patent37", "formula", "const_test"} <= set(models.registered_models())
    with pytest.raises(FormulaError, match="unknown signal 'statc'"):
        models.fit_model("statc", ds, "x")
    with pytest.raises(DataFormatError, match="no gyro_q"):
        models.fit_model("static", ds, "q")

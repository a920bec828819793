"""HRG models (seed 002): reverse/forward cubics on the paper's tables, eq-7 bias by LS and PSO."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.hrg import (
    fit_forward_cubic,
    fit_hrg,
    fit_hrg_forward,
    fit_hrg_pso,
    fit_hrg_reverse,
    fit_reverse_cubic,
    predict_hrg,
    predict_hrg_reverse,
)
from tests import REFERENCE_DIR

REF = REFERENCE_DIR
EQ2 = {"c3": -5.751e-7, "c2": -2.568e-4, "c1": 4.794e-1, "c0": 4.896e3}


def read_table(name: str) -> dict[str, np.ndarray]:
    with open(REF / name, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    return {h: np.array([float(r[i]) for r in rows[1:]]) for i, h in enumerate(rows[0])}


def table1_dataset() -> Dataset:
    t1 = read_table("hrg_frequency_temperature.csv")
    cols = {"time_s": np.arange(t1["chamber_c"].size) * 5 * 3600.0}
    for ch in ("x", "y", "z"):
        cols[f"freq_{ch}"] = t1[f"freq_g{ch}_hz"]
        cols[f"temp_t2{ch}"] = t1[f"ds18b20_g{ch}_c"]
    cols["temp_t1"] = t1["chamber_c"]
    return Dataset(cols)


def test_reverse_fit_reproduces_table2_gx():
    t2 = read_table("hrg_reverse_fit_gx.csv")
    rc = fit_reverse_cubic(t2["freq_hz"], t2["t2_c"])
    T4 = rc.evaluate(t2["freq_hz"])
    assert np.abs(T4 - t2["t2_c"]).max() <= 0.03
    assert np.abs(T4 - t2["t4_c"]).max() <= 0.03          # the paper's T4 column
    assert abs(rc.evaluate(rc.centre + rc.scale) - t2["t2_c"].max()) < 0.03


def test_reverse_adapter_on_table1_all_gyros():
    data = table1_dataset()
    for ch in ("x", "y", "z"):
        res = fit_hrg_reverse(data, ch, reference=f"t2{ch}")
        assert res.model == "hrg_reverse" and res.target == f"temp_t2{ch}"
        assert res.stats["max_abs_error_c"] <= 0.1          # paper's acceptance |T4 - T2| < 0.1 C
        assert set(res.coefficients) == {"a0", "a1", "a2", "a3"}
        assert res.definition["f_scale_hz"] > 0
        json.dumps(res.to_json())
    gx = fit_hrg_reverse(data, "x", reference="t2x")
    assert gx.stats["max_abs_error_c"] <= 0.03
    # evaluating from the stored definition only (what firmware does)
    d = gx.definition
    u = (data["freq_x"] - d["f_centre_hz"]) / d["f_scale_hz"]
    T = sum(gx.coefficients[f"a{i}"] * u ** i for i in range(4))
    pred, flagged = predict_hrg_reverse(gx, data)
    assert pred == pytest.approx(T) and not flagged.any()
    out = data.with_columns(freq_x=data["freq_x"] + 100.0)
    pred_out, flagged_out = predict_hrg_reverse(gx, out)
    assert flagged_out[data["freq_x"] + 100 > d["fmax_hz"]].all()
    assert pred_out.max() <= gx.validity["tmax_c"] + 0.05


def test_forward_cubic_matches_eq2_term_by_term_and_t3_column():
    t2 = read_table("hrg_reverse_fit_gx.csv")
    fc = fit_forward_cubic(t2["t2_c"], t2["freq_hz"])
    raw = fc.raw_coefficients()
    for name, paper in EQ2.items():
        assert raw[name] == pytest.approx(paper, rel=0.03), name
    T3 = fc.solve(t2["freq_hz"])
    assert np.abs(T3 - t2["t3_c"]).max() <= 0.01             # the paper's T3 column
    res = fit_hrg_forward(table1_dataset(), "x", reference="t2x")
    assert res.coefficients["c1"] == pytest.approx(EQ2["c1"], rel=0.03)


def test_bad_table_refused():
    with pytest.raises(DataFormatError, match="4 distinct"):
        fit_reverse_cubic(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    with pytest.raises(DataFormatError, match="temp_"):
        fit_hrg_reverse(table1_dataset(), "x")                # three probes: must choose one


# --- synthetic HRG thermal test (paper section 4: cool to -40 C, soak, heat at 1 C/min to 50 C) -----

K_TRUE = np.array([0.3, 0.02, -1.5e-4, -0.8, 0.6, 0.01])     # deg/h; T in C, dT/dt in C/min


def synthetic_hrg(seed: int = 0, dt: float = 10.0) -> Dataset:
    """Resonator temperature follows the chamber with a 15-min lag and +5 C self-heating; the
    frequency follows an eq-2-like cubic (+3 mHz noise); the DS18B20 reads it with 0.0625 C steps;
    the bias is eq 7 of the true temperature and rate plus white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 12 * 3600.0, dt)
    chamber = np.interp(t, [0, 7200, 10800, 16200, 43200], [20, -40, -40, 50, 50])
    T = np.empty(t.size)
    T[0] = 25.0
    a = dt / 900.0
    for i in range(1, t.size):
        T[i] = T[i - 1] + a * (chamber[i] + 5.0 - T[i - 1])
    rate = np.gradient(T, t / 60.0)
    freq = 4895.6 + 0.4793 * T - 2.574e-4 * T ** 2 - 5.6e-7 * T ** 3 + rng.normal(0, 0.003, t.size)
    probe = np.round((T + rng.normal(0, 0.02, t.size)) / 0.0625) * 0.0625
    bias = K_TRUE @ np.vstack([np.ones_like(T), T, T ** 2, rate, rate ** 2, T * rate]) + rng.normal(0, 0.3, t.size)
    return Dataset({"time_s": t, "freq_x": freq, "temp_t2": probe, "gyro_x": bias})


def test_eq7_least_squares_recovers_coefficients_from_frequency_temperature():
    data = synthetic_hrg()
    res = fit_hrg(data, "x", reference="t2")
    assert res.definition["temperature_source"]["kind"] == "reverse_cubic"
    k = np.array([res.coefficients[f"k{i}"] for i in range(6)])
    assert k[1] == pytest.approx(K_TRUE[1], rel=0.1)
    assert k[3] == pytest.approx(K_TRUE[3], rel=0.1)
    pred, flagged = predict_hrg(res, data)
    assert pred.shape == data["gyro_x"].shape and np.all(np.isfinite(pred))
    assert flagged.mean() < 0.05
    assert np.std(data["gyro_x"] - pred) < 1.05 * 0.3          # down to the white-noise floor
    assert np.std(data["gyro_x"]) > 1.9 * 0.3


def test_pso_within_half_percent_of_least_squares_cost():
    data = synthetic_hrg(1)
    res = fit_hrg_pso(data, "x", reference="t2", seed=3)
    s = res.stats
    assert s["cost_pso"] >= s["cost_ls"] * (1 - 1e-9)       # PSO cannot beat LS on a linear model
    assert s["cost_ratio"] <= 1.005                         # seeded with the LS particle
    # without the LS particle the paper's settings get close but stall in the correlated valley of
    # eq 7 (T*dT vs dT, T^2 vs 1): reported, loosely bounded here
    assert s["cost_ls"] <= s["cost_pso_unseeded"] <= 1.05 * s["cost_ls"]
    assert s["pso_seeded_with_ls"] is True and not s["ls_outside_bounds"]
    ls = fit_hrg(data, "x", reference="t2")
    assert ls.stats["cost_ls"] == pytest.approx(s["cost_ls"], rel=1e-9)
    json.dumps(res.to_json())


def test_compressed_cost_equals_direct_sse():
    from bench.fit.hrg import Eq7Problem
    rng = np.random.default_rng(5)
    T, r = rng.uniform(-40, 50, 500), rng.uniform(-1, 1, 500)
    y = 0.2 + 0.01 * T + 0.5 * r + rng.normal(0, 0.1, 500)
    prob = Eq7Problem(T, r, y)
    thetas = rng.normal(0, 1, (7, 6))
    direct = np.array([prob.sse_raw(prob.to_raw(th)) for th in thetas])
    assert prob.cost_std(thetas) * prob.ys ** 2 == pytest.approx(direct, rel=1e-9)

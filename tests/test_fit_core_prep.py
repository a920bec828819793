"""Preparation: Pauta, averaging, rates, Earth rate for the eight positions, installation matrix."""
from __future__ import annotations

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit import prep
from bench.fit.base import EARTH_RATE_DPH, Dataset
from tests.test_fit_core_synth import chamber_program, lag

LAT = 45.75


def test_pauta_rejects_spikes_on_residual_and_in_windows_not_the_trend():
    rng = np.random.default_rng(1)
    n = 20000
    t = np.arange(n, dtype=float)
    noise = rng.normal(0, 1, n)
    spikes = rng.choice(n, 20, replace=False)
    x = noise.copy()
    x[spikes] += 12.0
    keep = prep.pauta_mask(x)
    assert not keep[spikes].any()
    assert keep.sum() > n - 20 - 0.01 * n
    # on a trending raw signal the global criterion would be wrong; short windows are not
    trend = 0.01 * t + x
    keep_w = prep.pauta_mask(trend, time=t, window_s=60.0)
    assert not keep_w[spikes].any()
    assert keep_w.sum() > n - 20 - 0.01 * n


def test_block_average_100s_and_orientation_split():
    t = np.arange(1000, dtype=float)
    orient = np.array(["NUE"] * 550 + ["ENU"] * 450)
    ds = Dataset({"time_s": t, "gyro_x": t.copy(), "temp_t1": np.where(t == 5, np.nan, 1.0), "orientation": orient})
    avg = prep.block_average(ds, 100.0)
    # blocks restart at each orientation: 0..4 (NUE), 500-549 (NUE), 550-649 .. 950-999 (ENU)
    assert len(avg) == 11
    np.testing.assert_allclose(avg["gyro_x"][:2], [49.5, 149.5])
    assert avg["orientation"].tolist()[5:7] == ["NUE", "ENU"]
    np.testing.assert_allclose(avg["gyro_x"][5:7], [524.5, 599.5])
    np.testing.assert_allclose(avg["gyro_x"][-1], 974.5)
    assert avg["temp_t1"][0] == 1.0   # NaN ignored


def test_rate_is_the_smoothed_derivative_in_c_per_min():
    air = chamber_program([(25, 10), (85, 60), (85, 60)], 25.0)
    temp, true_rate = lag(air, 600.0, 25.0)
    rng = np.random.default_rng(2)
    t = np.arange(len(air), dtype=float)
    measured = np.round((temp + rng.normal(0, 0.01, len(t))) / 0.0625) * 0.0625
    rate = prep.rate_c_per_min(t, measured, 120.0)
    inner = slice(200, len(t) - 200)
    err = rate[inner] - true_rate[inner]
    assert np.max(np.abs(err)) < 0.03            # C/min, quantized probe
    assert abs(np.mean(err)) < 1e-3
    # a gap longer than half the window makes the rate NaN near the gap instead of inventing it
    keep = (t < 3000) | (t > 3300)
    r_gap = prep.rate_c_per_min(t[keep], measured[keep], 120.0)
    tk = t[keep]
    assert np.isnan(r_gap[(tk > 2950) & (tk < 3000)]).all()
    assert np.isfinite(r_gap[(tk > 3400) & (tk < 4000)]).all()


def test_earth_rate_for_the_eight_positions():
    c, s = EARTH_RATE_DPH * np.cos(np.radians(LAT)), EARTH_RATE_DPH * np.sin(np.radians(LAT))
    expected = {"ESD": (0, -c, -s), "USE": (s, -c, 0), "WSU": (0, -c, s), "DSW": (-s, -c, 0),
                "WND": (0, c, -s), "UNW": (s, c, 0), "ENU": (0, c, s), "DNE": (-s, c, 0), "NUE": (c, s, 0)}
    for code, vec in expected.items():
        np.testing.assert_allclose(prep.earth_rate_body(code, LAT), vec, atol=1e-12, err_msg=code)
    # sum over the eight positions cancels on every axis: bias = mean of the eight means
    total = sum(prep.earth_rate_body(code, LAT) for code in prep.EIGHT_POSITIONS)
    np.testing.assert_allclose(total, 0.0, atol=1e-12)
    with pytest.raises(ValueError):
        prep.orientation_axes("NEU")


def _eight_position_data(m_true, bias, noise=0.002, dwell=300, seed=0, channels=("1", "2", "3")):
    rng = np.random.default_rng(seed)
    a = np.linalg.inv(m_true)
    codes, rows = [], []
    for code in prep.EIGHT_POSITIONS:
        w = prep.earth_rate_body(code, LAT)
        rows.append(np.tile(bias + a @ w, (dwell, 1)))
        codes += [code] * dwell
    y = np.vstack(rows) + rng.normal(0, noise, (8 * dwell, 3))
    cols = {"time_s": np.arange(8 * dwell, dtype=float), "temp_t1": np.full(8 * dwell, 25.0),
            "orientation": np.array(codes)}
    for i, ch in enumerate(channels):
        cols[f"gyro_{ch}"] = y[:, i]
    return Dataset(cols, {"latitude_deg": str(LAT)})


def test_installation_matrix_and_bias_from_eight_positions():
    m_true = np.array([[1.0, 0.002, -0.003], [-0.0015, 1.0, 0.001], [0.0025, -0.002, 1.0]]) @ np.diag([1.0005, 0.9992, 1.0011])
    bias = np.array([0.152, -0.144, 0.0063])
    ds = _eight_position_data(m_true, bias)
    res = prep.eight_position(ds, ["1", "2", "3"])
    np.testing.assert_allclose(res.m, m_true, atol=5e-4)
    np.testing.assert_allclose([res.bias[c] for c in "123"], bias, atol=2e-4)
    assert res.residual_rms_dph < 1e-3
    # channel -> system axes (eq 1) with the estimated M reproduces the system-axis Earth rate
    sys_ds = prep.to_system_axes(ds.with_columns(**{f"gyro_{c}": ds[f"gyro_{c}"] - res.bias[c] for c in "123"}), res.m)
    omega = prep.body_earth_rates(ds)
    for i, ax in enumerate("xyz"):
        assert np.abs(sys_ds[f"gyro_{ax}"] - omega[:, i]).mean() < 5e-3
    back = prep.to_channel_axes(sys_ds, res.m)
    np.testing.assert_allclose(back["gyro_1"], ds["gyro_1"] - res.bias["1"], atol=1e-9)


def test_eight_position_refuses_too_few_positions():
    ds = _eight_position_data(np.eye(3), np.zeros(3))
    with pytest.raises(DataFormatError, match="at least 4 positions"):
        prep.eight_position(ds.select(ds.time < 900), ["1", "2", "3"])


def test_remove_earth_rate_leaves_the_bias():
    ds = _eight_position_data(np.eye(3), np.array([0.1, 0.2, 0.3]), noise=0.0, channels=("x", "y", "z"))
    out = prep.remove_earth_rate(ds)
    for i, ch in enumerate("xyz"):
        np.testing.assert_allclose(out[f"gyro_{ch}"], [0.1, 0.2, 0.3][i], atol=1e-12)
    with pytest.raises(DataFormatError, match="already removed"):
        prep.remove_earth_rate(out)
    with pytest.raises(DataFormatError, match="latitude"):
        prep.remove_earth_rate(Dataset(ds.columns, {}))
    # absent orientation column = NUE (S000: 北天东)
    plain = Dataset({"time_s": np.arange(3.0), "gyro_x": np.zeros(3), "temp_t1": np.zeros(3)}, {"latitude_deg": "0"})
    np.testing.assert_allclose(prep.remove_earth_rate(plain)["gyro_x"], -EARTH_RATE_DPH)


def test_bin_by_temperature_gives_equal_weight_per_bin():
    temp = np.r_[np.full(1000, 20.1), np.linspace(20.85, 30.35, 20)]
    y = temp * 2.0
    tm, (ym,), cnt = prep.bin_by_temperature(temp, y, bin_c=0.5)
    assert cnt[0] == 1000 and len(tm) == 21
    np.testing.assert_allclose(ym, tm * 2.0)


def test_rate_filter_equals_savitzky_golay_first_derivative():
    from scipy.signal import savgol_filter

    rng = np.random.default_rng(4)
    t = np.arange(5000.0) * 0.5
    x = np.cumsum(rng.normal(0, 0.01, t.size)) + 25.0
    ours = prep.rate_c_per_min(t, x, 60.0)                 # window 60 s = 121 samples at 2 Hz
    ref = savgol_filter(x, 121, polyorder=2, deriv=1, delta=0.5, mode="interp") * 60.0
    np.testing.assert_allclose(ours, ref, atol=1e-9)            # to the record's ends

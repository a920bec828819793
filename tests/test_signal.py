"""bench.signal: each shared operation pinned on inputs whose answer is known."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench import signal


def test_white_noise_allan_deviation_is_sigma_over_sqrt_tau():
    rng = np.random.default_rng(11)
    sigma, rate_hz = 2.0, 10.0
    x = rng.normal(0.0, sigma, 2 ** 16)
    res = signal.allan_deviation(x, rate_hz)
    expected = sigma / np.sqrt(res.taus_s * rate_hz)          # sigma of one sample is at tau = 1/rate
    short = res.taus_s <= 50.0                                 # enough pairs for a 10 % check
    np.testing.assert_allclose(res.adev[short], expected[short], rtol=0.1)
    assert res.dropped == 0


def test_allan_deviation_drops_nan_and_names_its_minimum():
    x = np.arange(20.0) % 3
    with_nan = np.r_[x[:10], np.nan, x[10:]]
    a, b = signal.allan_deviation(x, 1.0), signal.allan_deviation(with_nan, 1.0)
    np.testing.assert_array_equal(a.adev, b.adev)
    assert b.dropped == 1
    with pytest.raises(ValueError, match=f"at least {signal.MIN_ALLAN_SAMPLES} finite samples, got 7"):
        signal.allan_deviation(np.r_[np.ones(7), np.nan, np.nan], 1.0)
    with pytest.raises(ValueError, match="got 0"):
        signal.allan_deviation([], 1.0)


@pytest.mark.parametrize("method", signal.RATE_METHODS)
def test_linear_ramp_rate_in_c_per_min(method):
    t = np.arange(0.0, 3600.0, 2.0)
    temp = 20.0 + 1.5 * t / 60.0                                 # 1.5 C/min
    rate = signal.temperature_rate(t, temp, 120.0, method=method)
    np.testing.assert_allclose(rate, 1.5, rtol=1e-9)


@pytest.mark.parametrize("method", signal.RATE_METHODS)
def test_rate_follows_a_curving_temperature_to_the_records_ends(method):
    # a run that ends while the chamber still speeds up its cooling: within half a window of either
    # end the rate is the quadratic's slope at the sample, not the last full window's slope held
    t = np.arange(0.0, 3000.0)
    temp = 30.0 - t * t / 120_000.0                           # dT/dt = -t/1000 C/min
    rate = signal.temperature_rate(t, temp, 600.0, method=method)
    np.testing.assert_allclose(rate, -t / 1000.0, atol=1e-9)


def test_rate_method_must_be_known_and_time_comes_first():
    t = np.arange(100.0)
    with pytest.raises(ValueError, match="rate method 'diff' unknown"):
        signal.temperature_rate(t, t, 10.0, method="diff")
    # time first: swapping the arguments of a ramp gives 1/rate, not rate
    assert signal.temperature_rate(t, 2.0 * t, 10.0)[50] == pytest.approx(120.0)


def test_rate_beside_a_logger_outage_is_missing_or_the_slope_of_the_readings_present():
    # 1-s readings of a 3 C/min ramp with a 200-s outage: a 120-s window reaches into it for 59 s on
    # each side (less one sample).  By default the rate is missing there; asked for, it is the one-sided slope of what
    # was read, the true rate (an element does not stop heating while the logger is off)
    t = np.concatenate([np.arange(0.0, 1000.0), np.arange(1200.0, 2000.0)])
    temp = 0.05 * t
    near = (t > 999.0 - 60.0 + 1.0) & (t < 1200.0 + 60.0 - 1.0)
    missing = signal.temperature_rate(t, temp, 120.0)
    assert np.all(np.isnan(missing[near])) and np.allclose(missing[~near], 3.0)
    present = signal.temperature_rate(t, temp, 120.0, near_gaps="present")
    assert np.allclose(present, 3.0)
    with pytest.raises(ValueError, match="near_gaps"):
        signal.temperature_rate(t, temp, 120.0, near_gaps="zero")
    with pytest.raises(ValueError, match="no segments"):
        signal.temperature_rate(t, temp, 120.0, segments=[slice(0, 1000)], near_gaps="present")


def test_savgol_rate_restarts_at_each_segment():
    t = np.r_[np.arange(0.0, 600.0, 10.0), np.arange(0.0, 600.0, 10.0)]
    temp = np.r_[t[:60] / 60.0, 50.0 - 2.0 * t[60:] / 60.0]     # +1 then -2 C/min
    segs = signal.run_segments(t)
    assert segs == [slice(0, 60), slice(60, 120)]
    rate = signal.temperature_rate(t, temp, 100.0, method="savgol2", segments=segs)
    np.testing.assert_allclose(rate[:60], 1.0, atol=1e-9)
    np.testing.assert_allclose(rate[60:], -2.0, atol=1e-9)


def test_known_ar1_lag1_autocorrelation():
    rng = np.random.default_rng(3)
    phi, n = 0.7, 200_000
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert signal.lag1_autocorrelation(x) == pytest.approx(phi, abs=0.01)
    # pairs never cross a segment boundary; NaN dropped
    two = np.r_[np.zeros(5) + 1.0, -1.0, 1.0, -1.0]
    assert signal.lag1_autocorrelation(np.r_[1.0, 2.0, 3.0, np.nan, 4.0]) == pytest.approx(0.25)
    assert signal.lag1_autocorrelation(two, [slice(0, 5), slice(5, 8)]) == pytest.approx(-2.0 / 3.0)


def test_newey_west_lags():
    assert signal.newey_west_lags(4000) == int(np.floor(4 * 40 ** (2 / 9)))
    assert signal.newey_west_lags(0) == 1


def test_earth_rate_at_a_known_orientation_and_latitude():
    lat = 30.0
    omega = signal.EARTH_RATE_DPH
    assert omega == pytest.approx(15.0411, abs=1e-4)
    np.testing.assert_allclose(signal.earth_rate_enu(lat), [0.0, omega * math.sqrt(3) / 2, omega / 2], atol=1e-12)
    # NUE: x North, y Up, z East -> x reads the north component, y the vertical one, z nothing
    np.testing.assert_allclose(signal.earth_rate_body("NUE", lat), [omega * math.sqrt(3) / 2, omega / 2, 0.0],
                               atol=1e-12)
    # ESD: x East, y South, z Down
    np.testing.assert_allclose(signal.earth_rate_body("ESD", lat), [0.0, -omega * math.sqrt(3) / 2, -omega / 2],
                               atol=1e-12)
    per = signal.earth_rate_body_per_sample(np.array(["ESD", "", "ESD"], dtype=object), lat)
    np.testing.assert_allclose(per[1], signal.earth_rate_body("NUE", lat))
    with pytest.raises(signal.OrientationError, match="right-handed"):
        signal.earth_rate_body("NEU", lat)
    with pytest.raises(ValueError, match="upper-case"):
        signal.orientation_axes("nue")


def test_block_means_never_cross_a_segment_boundary():
    t = np.arange(300.0)
    x = np.where(t < 150, 1.0, 3.0)
    x[10] = np.nan
    segs = signal.run_segments(t, np.where(t < 150, "a", "b"))
    res = signal.block_means(t, {"x": x}, 100.0, segs)
    # segment a: 0-99, 100-149 (50 samples, kept); segment b aligned on 150: 150-249, 250-299
    np.testing.assert_array_equal(res.columns["x"], [1.0, 1.0, 3.0, 3.0])
    np.testing.assert_allclose(res.time_s, [49.5, 124.5, 199.5, 274.5])
    assert res.segments == [slice(0, 2), slice(2, 4)]
    np.testing.assert_array_equal(res.first_index, [0, 100, 150, 250])
    # without the segments the block 100-199 would mix both levels
    mixed = signal.block_means(t, {"x": x}, 100.0)
    np.testing.assert_allclose(mixed.columns["x"], [1.0, 2.0, 3.0])
    # a ragged end with less than half a block is dropped
    short = signal.block_means(np.arange(240.0), {"x": np.ones(240)}, 100.0)
    assert len(short.time_s) == 2


def test_block_means_of_a_time_axis_that_jumps_back_pool_the_same_block():
    # no segments given: a jump back in time puts its samples in the blocks their times fall in
    t = np.concatenate([np.arange(0.0, 300.0), np.arange(100.0, 200.0)])
    res = signal.block_means(t, {"x": t}, 100.0)
    np.testing.assert_allclose(res.columns["x"], [49.5, 149.5, 249.5])


def test_orientation_codes_per_sample_one_position_or_several():
    one = signal.earth_rate_body_per_sample(np.array(["", "ENU", ""], dtype=object), 45.0, default="ENU")
    np.testing.assert_allclose(one, np.tile(signal.earth_rate_body("ENU", 45.0), (3, 1)))
    codes = np.array(["NUE", "ENU", "", "NUE", "WSU"], dtype=object)
    per = signal.earth_rate_body_per_sample(codes, 45.0, default="ENU")
    for row, code in zip(per, ["NUE", "ENU", "ENU", "NUE", "WSU"]):
        np.testing.assert_allclose(row, signal.earth_rate_body(code, 45.0))
    axes = signal.orientation_axes_per_sample(codes)
    assert axes.shape == (5, 3, 3)
    np.testing.assert_allclose(axes[4], signal.orientation_axes("WSU"))


def test_lstsq_drops_non_finite_rows_and_survives_bad_scaling():
    t = np.linspace(-40.0, 80.0, 500)
    x = np.column_stack([np.ones_like(t), t, t ** 2 * 1e3, t ** 3])
    coef = np.array([1.0, -0.5, 2e-6, 1e-5])
    y = x @ coef
    y[7] = np.nan
    fit = signal.lstsq(x, y)
    np.testing.assert_allclose(fit.coef, coef, rtol=1e-8)
    assert fit.n == 499 and not fit.used[7] and np.isnan(fit.residual[7])


def test_hac_wald_test_chi2_rejects_a_real_term_and_not_a_junk_one():
    rng = np.random.default_rng(4)
    n = 2000
    t = np.arange(n, dtype=float)
    e = np.convolve(rng.normal(size=n + 20), np.ones(20) / 20, mode="valid")[:n]     # autocorrelated noise
    x = np.column_stack([np.ones(n), np.sin(t / 50.0), rng.normal(size=n)])
    y = 0.5 * x[:, 1] + e
    real = signal.hac_wald_test(x, y, [1])
    junk = signal.hac_wald_test(x, y, [2])
    assert real.distribution == "chi2" and real.df == 1
    assert real.p_value < 1e-6 and junk.p_value > 1e-3


def test_ols_hac_wald_and_ljung_box_agree_with_statsmodels():
    import statsmodels.api as sm
    from statsmodels.stats.diagnostic import acorr_ljungbox

    rng = np.random.default_rng(11)
    n = 300
    e = np.zeros(n)
    for i in range(1, n):                       # AR(1) errors: the case HAC exists for
        e[i] = 0.7 * e[i - 1] + rng.normal()
    x = np.column_stack([np.ones(n), np.linspace(-1, 1, n), rng.normal(size=n), np.sin(np.arange(n) / 9.0)])
    y = x @ np.array([1.0, 0.5, 0.0, 0.3]) + e
    ours = signal.ols_hac(x, y, maxlags=7)
    ref = sm.OLS(y, x).fit(cov_type="HAC", cov_kwds={"maxlags": 7})
    np.testing.assert_allclose(ours.params, ref.params, rtol=1e-10)
    np.testing.assert_allclose(ours.cov, ref.cov_params(), rtol=1e-9)
    np.testing.assert_allclose(ours.pvalues, ref.pvalues, rtol=1e-8)
    r = np.zeros((2, 4))
    r[0, 2] = r[1, 3] = 1.0
    want = ref.wald_test(r, scalar=True, use_f=False)
    scale = np.sqrt(np.mean(x ** 2, axis=0))
    got = signal.hac_wald_test(x * scale, y, [2, 3], maxlags=7)   # scaling does not change the test
    assert got.statistic == pytest.approx(float(want.statistic), rel=1e-8)
    assert got.p_value == pytest.approx(float(want.pvalue), rel=1e-6)
    q, p = signal.ljung_box(e, 10)
    lb = acorr_ljungbox(e - e.mean(), lags=[10], return_df=True)
    assert q == pytest.approx(float(lb["lb_stat"].iloc[0]), rel=1e-10)
    assert p == pytest.approx(float(lb["lb_pvalue"].iloc[0]), rel=1e-8, abs=1e-300)
    with pytest.raises(ValueError, match="ljung_box"):
        signal.ljung_box(np.ones(50), 5)

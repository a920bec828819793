"""The close-the-loop's numerical building blocks: the vectorised first-order recurrence (lags on
irregular time axes, the Duhem memory), the O(m) degrees of freedom of block means, the noise model
per contiguous stretch, and the spread the training noise puts into a validation error."""
from __future__ import annotations

import numpy as np
import pytest

from bench.fit.effects import duhem_state, first_order_lag, sample_period
from bench.fit.noisefloor import (_structure_ratio, block_covariance, block_means_edf, coefficient_spread,
                                  contiguous_pieces, fit_noise_model, realised_scale)
from bench.signal import linear_recurrence


def _loop(a, b, y0):
    out, y = np.empty(len(a)), y0
    for i in range(len(a)):
        y = a[i] * y + b[i]
        out[i] = y
    return out


def test_linear_recurrence_matches_the_loop_over_long_decays_and_resets():
    rng = np.random.default_rng(0)
    a = np.exp(-rng.exponential(0.5, 20_000))          # L falls by ~10,000: many chunks
    a[100] = 0.0                                        # a full reset
    b = rng.normal(size=20_000)
    assert np.max(np.abs(linear_recurrence(a, b, 3.0) - _loop(a, b, 3.0))) < 1e-9
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        linear_recurrence(np.array([1.5]), np.array([0.0]))


def test_duhem_memory_is_the_recurrence_it_defines():
    t = np.arange(0.0, 30_000.0, 10.0)
    temp = 20 * np.sin(t / 3000.0) + np.random.default_rng(1).normal(0, 0.05, len(t))
    rate = np.gradient(temp, t) * 60.0
    for width in (0.3, 4.0, 30.0):
        dT = rate * sample_period(t) / 60.0
        a = np.exp(-np.abs(dT) / width)
        assert np.max(np.abs(duhem_state(rate, t, width) - _loop(a, (1 - a) * np.sign(dT), 0.0))) < 1e-10


def _ramp_lag_loop(t, x, tau):
    """The lag's exact response to an input that is a straight line between samples, step by step:
    the forced response to the ramp (x - slope tau) plus the free decay of the rest."""
    y, out = x[0], np.empty(len(x))
    out[0] = y
    for i in range(1, len(x)):
        h = t[i] - t[i - 1]
        slope = (x[i] - x[i - 1]) / h
        y = (x[i] - slope * tau) + (y - (x[i - 1] - slope * tau)) * np.exp(-h / tau)
        out[i] = y
    return out


def test_first_order_lag_steps_over_a_logger_outage_by_its_length():
    t = np.concatenate([np.arange(0.0, 3000.0), np.arange(4800.0, 8000.0)])   # 30 min missing
    x = np.where(t < 1000, 0.0, 10.0)
    y = first_order_lag(x, t, 600.0)
    i = int(np.searchsorted(t, 4800.0))
    # over the outage the lag keeps relaxing towards 10 for 1800 s (not one sample period)
    expected = 10.0 + (y[i - 1] - 10.0) * np.exp(-1801.0 / 600.0)
    assert y[i] == pytest.approx(expected, rel=1e-9)
    # a temperature that kept ramping through the outage: the lag follows the straight line between
    # the readings either side, not the reading after the outage held for all of it
    ramp = 0.01 * t
    assert np.max(np.abs(first_order_lag(ramp, t, 600.0) - _ramp_lag_loop(t, ramp, 600.0))) < 1e-9
    # a ramp from rest: after the transient the lag trails the ramp by slope x tau
    assert first_order_lag(ramp, t, 600.0)[-1] == pytest.approx(ramp[-1] - 0.01 * 600.0, abs=1e-3)
    u = np.arange(0.0, 5000.0)
    assert np.max(np.abs(first_order_lag(np.sin(u / 500.0), u, 600.0) - _ramp_lag_loop(u, np.sin(u / 500.0), 600.0))) < 1e-10
    # a failed conversion is interpolated between its neighbours
    v = np.sin(u / 500.0)
    gappy = v.copy()
    gappy[1000:1003] = np.nan
    assert np.max(np.abs(first_order_lag(gappy, u, 60.0) - first_order_lag(v, u, 60.0))) < 1e-5


def test_block_means_edf_equals_the_dense_covariance_formula():
    for m in (2, 12, 300):
        for parts in ({-1.0: 1.0}, {0.0: 1.0}, {-2.0: 0.1, -1.0: 0.3, 0.0: 1.0}):
            lags = np.abs(np.arange(m)[:, None] - np.arange(m)[None, :])
            g = np.zeros((m, m))
            for mu, av in parts.items():
                g -= av * _structure_ratio(lags, mu)
            c = g - g.mean(axis=0, keepdims=True)
            c = c - c.mean(axis=1, keepdims=True)
            assert block_means_edf(m, parts) == pytest.approx(np.trace(c) ** 2 / np.sum(c * c), rel=1e-9)
    assert block_means_edf(288, {-1.0: 1.0}) == pytest.approx(287.0)


def test_noise_model_ignores_steps_across_outages_and_missing_stretches():
    rng = np.random.default_rng(2)
    t = np.arange(40_000.0)
    x = rng.normal(0, 0.05, len(t)) + np.where(t < 20_000, 0.0, 5.0)   # a jump where the logger was out
    keep = (t < 20_000) | (t >= 22_000)
    pieces = contiguous_pieces(x[keep], 1.0, t[keep])
    assert [len(p) for p in pieces] == [20_000, 18_000]
    joined = fit_noise_model([(x[keep], 1.0)])
    split = fit_noise_model([(x[keep], 1.0, t[keep])])
    assert split.floor(20_000)["noise_floor_dph"] == pytest.approx(0.005, rel=0.15)
    # joined end to end, the jump dominates the long-tau Allan deviation; split, it is not there
    assert joined.adev[-1] > 50 * split.adev[-1]
    assert split.adev[-1] < 2 * 0.05 / np.sqrt(split.taus[-1])
    y = x.copy()
    y[20_000:22_000] = np.nan
    assert [len(p) for p in contiguous_pieces(y, 1.0)] == [20_000, 18_000]


def test_coefficient_spread_predicts_the_validation_error_of_a_true_form_model():
    rng = np.random.default_rng(5)
    m = 300
    tr = np.linspace(-1, 1, m)
    X = np.column_stack([np.ones(m), tr, tr ** 2])
    V = np.column_stack([np.ones(200), np.sin(np.arange(200) / 15.0), np.sin(np.arange(200) / 15.0) ** 2])
    model = fit_noise_model([(rng.normal(0, 1.0, 300_000), 1.0)])   # white: 0.1 per 100-s mean
    spread = coefficient_spread(model, X, np.arange(m), V)
    extra = []
    for _ in range(400):
        y = rng.normal(0, 0.1, m)                                     # 100-s means of the noise
        b = np.linalg.lstsq(X, y, rcond=None)[0]
        extra.append(np.var(V @ b, ddof=1))
    assert spread.variance == pytest.approx(np.mean(extra), rel=0.15)
    assert 1.0 <= spread.edf <= 2.0 + 1e-9          # two non-constant columns


def test_gls_f_test_holds_its_level_under_flicker_noise_where_hac_does_not():
    # white + flicker (1/f) rate noise, 10 h at 1 s, tested on 100-s means against a slow regressor
    # (a linear time drift) that is not there: under the noise model fitted from the residual's own
    # Allan variance, the GLS F test rejects at about its nominal rate; the Newey-West Wald test,
    # blind to the long memory of 1/f noise, rejects far more often
    from bench.fit.closeloop_search import hac_wald_p
    from bench.fit.noisefloor import block_covariance, fit_noise_model, gls_f_test, gls_whitener

    rng = np.random.default_rng(5)
    n = 36000
    f = np.fft.rfftfreq(2 * n, 1.0)
    shape = np.zeros_like(f)
    shape[1:] = 1.0 / np.sqrt(f[1:])
    t = np.arange(n, dtype=float)
    X0 = np.ones((n // 100, 1))
    X1 = np.column_stack([X0, (t / 3600.0).reshape(-1, 100).mean(axis=1)])
    gls, hac = [], []
    for _ in range(40):
        flick = np.fft.irfft((rng.normal(size=len(f)) + 1j * rng.normal(size=len(f))) * shape)[:n]
        y = rng.normal(size=n) + 0.15 * flick / flick.std()
        model = fit_noise_model([(y - y.mean(), 1.0, t)])
        yb = y.reshape(-1, 100).mean(axis=1)
        W = gls_whitener(block_covariance(model, np.arange(len(yb))))
        gls.append(gls_f_test(W, X0, X1, yb)[1])
        hac.append(hac_wald_p(X1, yb, [1]))
    assert np.mean(np.array(gls) < 0.05) <= 0.15
    assert np.mean(np.array(hac) < 0.05) >= 0.25


def _white_plus_flicker(rng, n: int, white: float, flicker_adev: float) -> np.ndarray:
    """White rate noise plus flicker whose Allan deviation is ``flicker_adev`` (one-sided PSD h/f,
    Allan variance 2 ln2 h)."""
    f = np.fft.rfftfreq(4 * n, 1.0)
    amp = np.zeros_like(f)
    amp[1:] = np.sqrt(flicker_adev ** 2 / (2 * np.log(2)) / f[1:] / 2.0)    # unit white: one-sided PSD 2
    x = np.fft.irfft(np.fft.rfft(rng.normal(size=4 * n)) * amp, 4 * n)[:n]
    return rng.normal(0, white, n) + x


@pytest.mark.parametrize("dt,corr_s", [(1.0, 3.0), (0.1, 1.0)])
def test_a_sensor_filtered_below_its_output_rate_gets_the_floor_of_its_100_s_means(dt, corr_s):
    # a gyro whose output is low-pass filtered (first order, time constant corr_s) and sampled faster
    # than that: its Allan variance rises up to corr_s before it falls as white noise.  Read as flicker,
    # that rise once made the floor 2.8x (1 s) and 3.6x (0.1 s) the std of the record's 100-s means
    from scipy.signal import lfilter

    rng = np.random.default_rng(11)
    n = int(20_000 / dt)
    a = np.exp(-dt / corr_s)
    ratios, corrs = [], []
    for _ in range(6):
        x = lfilter([1 - a], [1, -a], _white_plus_flicker(rng, n, 0.15 / np.sqrt(dt), 0.008))
        model = fit_noise_model([(x, dt, np.arange(n) * dt)])
        k = int(round(100 / dt))
        ratios.append(np.std(x[: n // k * k].reshape(-1, k).mean(axis=1), ddof=1)
                      / model.floor(n * dt)["noise_floor_dph"])
        corrs.append(model.white_corr_s)
    assert 0.85 < np.median(ratios) < 1.15
    assert corr_s / 2 <= np.median(corrs) <= 2 * corr_s


def test_white_noise_sampled_at_its_bandwidth_has_no_correlation_time():
    rng = np.random.default_rng(12)
    model = fit_noise_model([(_white_plus_flicker(rng, 20_000, 0.15, 0.008), 1.0)])
    assert model.white_corr_s == 0.0
    assert model.summary()["white_correlation_s"] == 0.0


def test_floor_over_judged_blocks_keeps_the_span_of_a_gap_and_its_limit_holds_its_level():
    # two stretches of 1.7 h judged, 4 h apart: flicker over the span they cover, not over 120
    # consecutive blocks; the noise level fitted from the data each time, its limit exceeded about
    # as rarely as its level says
    rng = np.random.default_rng(8)
    n = 30_000
    t = np.arange(float(n))
    judged = (t < 6000) | ((t >= 20_000) & (t < 26_000))
    idx = np.concatenate([np.arange(60), np.arange(200, 260)])
    stds, over, consecutive, limits = [], [], [], []
    for _ in range(150):
        x = _white_plus_flicker(rng, n, 0.1, 0.01)
        stds.append(np.std(x[judged].reshape(-1, 100).mean(axis=1), ddof=1))
        model = fit_noise_model([(np.where(judged, x, np.nan), 1.0, t)])
        fl = model.floor_over(idx)
        over.append(fl["noise_floor_dph"] ** 2)
        limits.append(fl["limit_dph"])
        consecutive.append(model.floor(120 * 100.0)["noise_floor_dph"] ** 2)
    stds = np.array(stds)
    assert np.mean(over) == pytest.approx(np.mean(stds ** 2), rel=0.12)
    assert np.mean(consecutive) < 0.9 * np.mean(stds ** 2)
    assert np.mean(stds > np.array(limits)) <= 0.03


def test_flicker_is_seen_across_dropped_rows_through_block_means():
    # a logger that drops a row every 200-400 s leaves stretches too short for Allan taus where
    # flicker shows; the 100-s block means numbered by time reach them across the drops
    rng = np.random.default_rng(9)
    n = 40_000
    t = np.arange(float(n))
    keep = np.ones(n, dtype=bool)
    drops = np.cumsum(rng.integers(200, 400, n // 150))
    keep[drops[drops < n - 1]] = False
    got = []
    for _ in range(20):
        x = _white_plus_flicker(rng, n, 0.2, 0.01)
        model = fit_noise_model([(x[keep], 1.0, t[keep])])
        got.append(model.coef[0.0] / 0.01 ** 2)
        assert model.tau_max_s >= 800.0
    got = np.array(got)
    assert 0.8 < np.median(got) < 1.25, got
    assert np.mean((got > 0.5) & (got < 1.6)) >= 0.8, got      # stretches alone: about half of them


def test_a_slow_structure_that_hides_the_noise_level_is_never_called_noise():
    # 10-s samples whose random walk and bias step dominate the Allan variance from 20 s on: the short
    # taus cannot tell white from flicker, so the fitted noise level is nearly unknown; its limit
    # used to widen with that (up to 10^4 x the floor) and passed std100s of 8-28x the floor as noise
    from bench.fit.closeloop import at_floor
    from bench.fit.metrics import window_means, window_numbers

    called_noise = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        t = np.arange(0.0, 20_000.0, 10.0)
        x = rng.normal(0, 0.05, t.size) + np.cumsum(rng.normal(0, 0.01, t.size)) + np.where(t > 12_000, 0.5, 0.0)
        floor = fit_noise_model([(x, 10.0, t)]).floor_over(window_numbers(t, x, 100.0))
        std = float(np.nanstd(window_means(t, x, 100.0), ddof=1))
        assert std > 3 * floor["noise_floor_dph"]
        called_noise.append(at_floor(std, floor))
    assert not any(called_noise), called_noise


def test_a_noise_model_claims_no_more_variance_over_a_span_than_its_residual_realises():
    # the residual's Allan variance at short taus read as a rate random walk carried over a long span
    # claims a large variance of its block means; over the blocks that realise less, its level is
    # brought down to theirs, and a model the blocks agree with (or exceed) is left as it is
    from bench.fit.metrics import window_means

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 40_000.0, 1.0)
    white = rng.normal(0, 0.2, t.size)
    model = fit_noise_model([(white + np.cumsum(rng.normal(0, 0.002, t.size)), 1.0, t)])
    assert model.summary()["rate_random_walk_dph_per_rt_s"] > 0
    idx = np.arange(400)
    g = block_covariance(model, idx, mus=(-2.0, -1.0, 0.0, 1.0))
    a = np.eye(len(idx)) - 1.0 / len(idx)
    expected = np.trace(a @ g @ a) / (len(idx) - 1)
    quiet = window_means(t, white, 100.0)
    scale = realised_scale(g, quiet)
    assert scale == pytest.approx(np.var(quiet, ddof=1) / expected) and scale < 0.5
    # the scaled model's expected variance is what the blocks hold
    assert np.trace(a @ (scale * g) @ a) / (len(idx) - 1) == pytest.approx(np.var(quiet, ddof=1))
    loud = quiet + np.linspace(-1.0, 1.0, len(quiet))
    assert np.var(loud, ddof=1) > expected and realised_scale(g, loud) == 1.0
    assert realised_scale(g, quiet[:1]) == 1.0

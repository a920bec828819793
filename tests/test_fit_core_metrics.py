"""Metrics: bias stability (1 and 3 sigma), repeatability, Allan readings, correlation of profiles."""
from __future__ import annotations

import numpy as np
import pytest

from bench.fit import metrics


def test_bias_stability_of_white_noise_is_sigma_over_ten():
    rng = np.random.default_rng(5)
    t = np.arange(200_000, dtype=float)
    x = rng.normal(0.0, 0.5, t.size)
    s = metrics.bias_stability(t, x)
    assert s == pytest.approx(0.05, rel=0.08)
    assert metrics.bias_stability_3sigma(t, x) == pytest.approx(3 * s)
    # a trend is what stability is meant to reveal
    assert metrics.bias_stability(t, x + t * 1e-5) > 5 * s
    # a final partial window (here 10 samples) is ignored
    assert len(metrics.window_means(np.arange(1010.0), np.ones(1010))) == 10


def test_bias_repeatability_is_the_std_of_run_biases():
    assert metrics.bias_repeatability([1.0, 2.0, 3.0]) == pytest.approx(1.0)
    assert np.isnan(metrics.bias_repeatability([1.0]))


def test_allan_readings_for_white_noise_and_rate_random_walk():
    rng = np.random.default_rng(7)
    n = 2 ** 17
    white, k_s = 1.0, 0.01            # deg/h at tau = 1 s ; deg/h/sqrt(s)
    x = rng.normal(0, white, n) + np.cumsum(rng.normal(0, k_s, n))
    res = metrics.allan(x, rate_hz=1.0)
    assert res.adev_at_1s_dph == pytest.approx(white, rel=0.05)
    assert res.arw_deg_per_rt_h == pytest.approx(white / 60.0, rel=0.05)
    assert res.bias_instability_dph == pytest.approx(res.adev.min() / 0.664)
    assert res.rrw_dph_per_rt_h == pytest.approx(k_s * 60.0, rel=0.3)
    assert np.all(np.diff(res.taus) > 0) and res.taus[0] == 1.0
    # 10 Hz data: tau = 1 s is interpolated; ARW unchanged in deg/sqrt(h)
    x10 = rng.normal(0, white * np.sqrt(10), 2 ** 16)
    res10 = metrics.allan(x10, rate_hz=10.0)
    assert res10.adev_at_1s_dph == pytest.approx(white, rel=0.05)
    assert res10.rrw_dph_per_rt_h is None or res10.rrw_dph_per_rt_h < 0.2


def test_profile_correlation_aligns_on_elapsed_time_and_truncates():
    t_a = np.arange(0.0, 20000.0, 1.0)
    t_b = 5000.0 + np.arange(0.0, 12000.0, 2.0)     # other start time, period, and length
    prof = lambda e: 20 * np.sin(2 * np.pi * e / 8000.0)  # noqa: E731
    same = metrics.profile_correlation(t_a, prof(t_a), t_b, prof(t_b - 5000.0))
    assert same == pytest.approx(1.0, abs=1e-6)
    quarter = metrics.profile_correlation(t_a, prof(t_a), t_b, 20 * np.cos(2 * np.pi * (t_b - 5000.0) / 8000.0))
    assert abs(quarter) < 0.1
    assert metrics.weakly_correlated(quarter) and not metrics.weakly_correlated(same)
    assert not metrics.weakly_correlated(-0.9) and metrics.weakly_correlated(-0.9, absolute=False)
    assert metrics.improvement_pct(10.0, 4.0) == pytest.approx(60.0)


def test_residual_summary_keys():
    rng = np.random.default_rng(1)
    t = np.arange(5000.0)
    out = metrics.residual_summary(t, rng.normal(0, 0.1, t.size))
    assert {"rms_dph", "p2p_dph", "std100_dph", "std100_3sigma_dph", "arw_deg_per_rt_h",
            "bias_instability_dph"} <= set(out)
    assert out["rms_dph"] == pytest.approx(0.1, rel=0.05)

"""The trend test of close-the-loop's structure description: the slope of the residual's 100-s means is
judged against the larger of its Newey-West variance and the variance the fitted noise model puts into
it, so flicker noise's wander over a long record is not read as a trend, a trend beyond the noise is,
and a stretch left out of the judged part keeps its length on the time axis."""
from __future__ import annotations

import numpy as np

from bench.fit.closeloop import linear_trend
from bench.fit.metrics import window_means
from bench.signal import ols_hac
from tests.test_closeloop_periodic import _flicker, false_alarm_rates
from tests.test_closeloop_periodic import judged_against_own_noise_model as _judge


def _hac_slope_says_trend(x: np.ndarray, t: np.ndarray, judged: dict) -> bool:
    means = window_means(t, x, 100.0)
    tt = np.arange(len(means)) / 36.0
    return ols_hac(np.column_stack([np.ones(len(means)), tt]), means).pvalues[1] < 0.01


def test_flicker_noise_alone_shows_no_trend_under_its_own_noise_model():
    # white + strong flicker over 5.6 h: a HAC slope test with a few lags rejects far more often than
    # its 1 % level; against the noise model's variance of the slope it does not
    judged, plain = false_alarm_rates(21, "trend", _hac_slope_says_trend)
    assert judged <= 0.05, judged
    assert plain > 3 * max(judged, 0.05), (plain, judged)


def test_a_trend_beyond_the_noise_is_found_with_its_slope():
    rng = np.random.default_rng(22)
    n = 20_000
    t = np.arange(float(n))
    for _ in range(5):
        x = rng.normal(0, 0.1, n) + 0.005 * _flicker(rng, n) + 0.008 * t / 3600.0
        st = _judge(x, t)
        assert "trend" in st["failed_tests"], st
        assert abs(st["trend_dph_per_h"] - 0.008) < 0.003, st["trend_dph_per_h"]


def test_a_left_out_stretch_keeps_its_length_on_the_time_axis():
    # blocks 0-9 and 30-39 of a line rising 0.01 deg/h per hour: numbered by their place in the record
    # the slope is the line's; numbered one after another it would come out three times too steep
    index = np.r_[np.arange(10), np.arange(30, 40)].astype(float)
    means = 0.01 * index * 100.0 / 3600.0
    white = np.eye(len(index)) * 1e-6
    st = linear_trend(means, index, white)
    assert abs(st["trend_dph_per_h"] - 0.01) < 1e-12, st
    assert st["trend_p"] < 1e-6, st


def _report(verdict: str, dropped: list[dict], failed: list[str]) -> dict:
    errors = {"validation_std100_dph": 0.0161, "validation_coverage": 1.0, "validation_all_std100_dph": 0.0161}
    return {"declared_model": "t1 + t1^2 + t1^3", "before": {**errors, "validation_std100_dph": 0.0926},
            "after": errors, "noise_floor": {"noise_floor_dph": 0.0146, "interval_dph": [0.0132, 0.0161]},
            "probes_not_searched": [], "effects_added": [], "effects_not_generalised": dropped,
            "structure": {"train": {"testable": True}, "validation": {
                "testable": True, "ratio_to_noise_floor": 1.10, "failed_tests": failed,
                "trend_dph_per_h": 0.002, "ljung_box_p": 0.4, "peak_period_s": 400.0, "peak_amplitude_dph": 0.003}},
            "verdict": verdict, "verdict_judged_on": "validation (in range)"}


def test_findings_give_effects_that_did_not_generalise_as_why_a_channel_is_partly_explained():
    from bench.fit.closeloop import _findings

    lag = {"kind": "thermal_lag", "params": {"probe": "t4", "tau_s": 242.0}, "status": "did not generalise",
           "validation_std100_with_dph": 0.01594, "validation_std100_without_dph": 0.01577}
    text = _findings(_report("partly_explained", [lag], []))
    assert "not fully explained: effects chosen on the training run did not generalise" in text, text
    # a trend the test finds is named beside it; a channel with nothing dropped gives only what the tests find
    assert "a trend of 0.002 deg/h per hour" in _findings(_report("partly_explained", [lag], ["trend"]))
    alone = _findings(_report("partly_explained", [], ["trend"]))
    assert "did not generalise" not in alone and "a trend of 0.002" in alone, alone

"""The periodic test of close-the-loop's structure description: a period is claimed only when the
peak is significant against the residual's own noise (white + flicker, not white alone), at least two
periods fit in the span, and a sine beats a cubic in time."""
from __future__ import annotations

import numpy as np

from bench.fit.closeloop import describe_structure
from bench.fit.metrics import window_numbers
from bench.fit.noisefloor import block_covariance, fit_noise_model


def _flicker(rng, n: int) -> np.ndarray:
    f = np.fft.rfftfreq(2 * n, 1.0)
    shape = np.zeros_like(f)
    shape[1:] = 1.0 / np.sqrt(f[1:])
    x = np.fft.irfft((rng.normal(size=len(f)) + 1j * rng.normal(size=len(f))) * shape)[:n]
    return x / np.std(x)


def judged_against_own_noise_model(x: np.ndarray, t: np.ndarray) -> dict:
    """``describe_structure`` of a residual against its own fitted noise model (the floor over its
    blocks, the null their covariance), with that floor as ``floor``."""
    model = fit_noise_model([(x - x.mean(), 1.0, t)])
    idx = window_numbers(t, x, 100.0)
    floor = model.floor_over(idx)["noise_floor_dph"]
    return {**describe_structure(x, t, floor, block_covariance(model, idx)), "floor": floor}


def false_alarm_rates(seed: int, test: str, plain, draws: int = 60, n: int = 20_000) -> tuple[float, float]:
    """Over ``draws`` residuals of white + strong flicker noise and nothing else: the share that fail
    ``test`` judged against their own noise model, and the share where ``plain(x, t, judged)`` (a test
    that does not know the noise model) says there is structure."""
    rng = np.random.default_rng(seed)
    t = np.arange(float(n))
    judged, plain_says = [], []
    for _ in range(draws):
        x = rng.normal(0, 0.1, n) + 0.02 * _flicker(rng, n)
        st = judged_against_own_noise_model(x, t)
        judged.append(test in st["failed_tests"])
        plain_says.append(bool(plain(x, t, st)))
    return float(np.mean(judged)), float(np.mean(plain_says))


def test_a_wave_longer_than_half_the_record_is_not_a_period():
    # a 5000-s sine in a 6000-s record: far above the noise, but less than two periods fit and a cubic
    # in time describes it as well; it must not be reported as a periodic component
    rng = np.random.default_rng(1)
    t = np.arange(6000.0)
    for phase in (0.0, 1.0, 2.0):
        r = 0.05 * np.sin(2 * np.pi * t / 5000.0 + phase) + rng.normal(0, 0.05, len(t))
        st = describe_structure(r, t, 0.005)
        assert "periodic" not in st["failed_tests"], st
        assert not st.get("better_than_cubic", False) or st["peak_p"] >= 0.01, st


def test_a_resolved_period_is_found_with_its_period():
    rng = np.random.default_rng(2)
    t = np.arange(6000.0)
    r = 0.02 * np.sin(2 * np.pi * t / 1500.0) + rng.normal(0, 0.05, len(t))
    st = describe_structure(r, t, 0.005)
    assert "periodic" in st["failed_tests"], st
    assert abs(st["peak_period_s"] - 1500.0) / 1500.0 < 0.05
    assert 0.015 < st["peak_amplitude_dph"] < 0.025


def test_a_period_across_an_outage_keeps_the_outage_length():
    # two stretches of a 1200-s sine with 2000 s missing between them: block numbers keep the lag,
    # so the period is found (joined end to end the phase would jump)
    rng = np.random.default_rng(3)
    t = np.concatenate([np.arange(0.0, 5000.0), np.arange(7000.0, 12000.0)])
    r = 0.02 * np.sin(2 * np.pi * t / 1200.0) + rng.normal(0, 0.05, len(t))
    st = describe_structure(r, t, 0.005)
    assert "periodic" in st["failed_tests"], st
    assert abs(st["peak_period_s"] - 1200.0) / 1200.0 < 0.03


def test_flicker_noise_alone_is_not_periodic_against_its_own_noise_model():
    # white + strong flicker, nothing else: against a white null (the floor alone) the red low
    # frequencies look like a period far more often than the 1 % level; against the noise model's
    # covariance of the block means they do not
    red_null, white_null = false_alarm_rates(
        4, "periodic", lambda x, t, st: describe_structure(x, t, st["floor"]).get("peak_p", 1.0) < 0.01)
    assert red_null <= 0.05, red_null
    assert white_null > 2 * max(red_null, 0.02), (white_null, red_null)

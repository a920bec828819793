"""Synthetic thermal runs with known truth for the fitting-core tests (numpy only).

Physics (kept simple and honest): the chamber air follows a piecewise-linear program; each probe is a
first-order lag of the air (time constant tau_i, integrated exactly per 1-s step); the base probe t2
also sees the gyro's own warm-up after power-on (+warm_c (1 - exp(-t/2400 s))), so the gradient
t1 - t2 is not just proportional to the ramp rate; recorded probes are quantized to 0.0625 C
(DS18B20 12-bit).  The true bias is computed from the *true* probe temperatures and their exact
derivatives (C/min), plus white noise.
"""
from __future__ import annotations

import numpy as np

from bench.fit.base import Dataset

TAUS = {"t1": 600.0, "t2": 900.0, "t3": 1200.0, "t4": 300.0}
STATIC_TRUE = {"A0": 0.152, "A1": 1.36e-2, "A2": 5.66e-4, "A3": 1.64e-5}
DYNAMIC_TRUE = {"B0": 0.30, "k": -0.014, "p": 0.25, "q": 0.14}


def chamber_program(segments: list[tuple[float, float]], start_c: float, dt: float = 1.0) -> np.ndarray:
    """segments: (target C, rate C/min or 0 = hold for `target` seconds given as negative?) -> air temp.

    Each segment is (target_c, minutes): ramp linearly from the current value to target_c over the
    given minutes (equal target = hold)."""
    out = [np.array([start_c])]
    cur = start_c
    for target, minutes in segments:
        n = int(round(minutes * 60.0 / dt))
        out.append(np.linspace(cur, target, n + 1)[1:])
        cur = target
    return np.concatenate(out)


def lag(air: np.ndarray, tau: float, start: float, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact first-order lag of a piecewise-linear input sampled every dt; returns (T, dT/dt in C/min)."""
    a = np.exp(-dt / tau)
    out = np.empty_like(air)
    out[0] = start
    for i in range(1, len(air)):   # ramp-exact discretisation of dT/dt = (u - T)/tau
        u0, u1 = air[i - 1], air[i]
        slope = (u1 - u0) / dt
        out[i] = a * out[i - 1] + (1 - a) * (u0 - slope * tau) + slope * dt
    rate = (air - out) / tau * 60.0
    return out, rate


def thermal_run(segments, start_c=25.0, *, seed=0, noise_dph=0.05, warm_c=4.0, truth="static",
                coeffs=None, quantize=True, probes=("t1", "t2", "t3", "t4")) -> tuple[Dataset, dict]:
    rng = np.random.default_rng(seed)
    air = chamber_program(segments, start_c)
    n = len(air)
    t = np.arange(n, dtype=np.float64)
    true_t, true_r = {}, {}
    for p in probes:
        true_t[p], true_r[p] = lag(air, TAUS[p], start_c)
    warm = warm_c * (1.0 - np.exp(-t / 2400.0))
    true_t["t2"] = true_t["t2"] + warm
    true_r["t2"] = true_r["t2"] + warm_c / 2400.0 * np.exp(-t / 2400.0) * 60.0
    noise = rng.normal(0.0, noise_dph, n)
    if truth == "static":
        c = coeffs or STATIC_TRUE
        d = true_t["t1"] - 25.0
        bias = c["A0"] + c["A1"] * d + c["A2"] * d ** 2 + c["A3"] * d ** 3
    elif truth == "dynamic":
        c = coeffs or DYNAMIC_TRUE
        bias = c["B0"] + c["k"] * (true_t["t1"] - 25.0) + c["p"] * (true_t["t1"] - true_t["t2"]) + c["q"] * true_r["t1"]
    elif callable(truth):
        bias = truth(true_t, true_r)
    else:
        raise ValueError(truth)
    cols = {"time_s": t, "gyro_x": bias + noise}
    for p in probes:
        v = true_t[p]
        cols[f"temp_{p}"] = np.round(v / 0.0625) * 0.0625 if quantize else v.copy()
    cols["chamber_pv"] = air
    ds = Dataset(cols, {"gyro_id": "SYN-1", "sample_period_s": "1.0"})
    return ds, {"bias": bias, "noise": noise, "true_t": true_t, "true_r": true_r}


CAL_PROFILE = [(25, 20), (-20, 45), (-20, 60), (10, 15), (10, 40), (60, 25), (60, 60), (35, 50), (35, 30),
               (45, 5), (45, 40), (25, 40), (25, 20)]
# validation run: different rates/levels, |r| with CAL_PROFILE = 0.23 (S001 weak-correlation rule)
VAL_PROFILE = [(25, 30), (40, 30), (40, 40), (0, 80), (0, 40), (50, 60), (50, 40), (-10, 90), (-10, 30), (25, 40),
               (25, 20)]


def test_lag_is_exact_for_a_ramp():
    air = chamber_program([(85, 60)], 25.0)          # 1 C/min ramp
    temp, rate = lag(air, 300.0, 25.0)
    # steady ramp response: T = u - r tau (1 - exp(-t/tau))
    tt = np.arange(len(air))
    expected = air - (1 / 60) * 300.0 * (1 - np.exp(-tt / 300.0))
    assert np.max(np.abs(temp - expected)) < 1e-9
    assert abs(rate[-1] - 1.0 * (1 - np.exp(-3600 / 300))) < 1e-6

"""The physical effects of the fourth referee, defined once on a ``Signals`` view.

The generator evaluates them on the true (smooth) probe temperatures at the physics step; the oracle
evaluates the same definitions on what the logger recorded.  Temperatures in C, rates in C/min,
time in s.  Every effect returns a regressor whose coefficient (deg/h per unit) the case draws.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

T_REF_C = 25.0
RATE_WINDOW_S = 120.0


@dataclass
class Signals:
    """Time base, temperatures and rates of one run, and its power-on instants."""
    t: np.ndarray
    temps: dict[str, np.ndarray]
    rates: dict[str, np.ndarray]
    power_on_s: list[float]

    def temp(self, probe: str) -> np.ndarray:
        return self.temps[probe]

    def rate(self, probe: str) -> np.ndarray:
        return self.rates[probe]


def lag_irregular(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag on any time base, exact for an input linear between samples (so it steps
    over a logger outage by its length, with the temperature interpolated across it)."""
    y = np.empty_like(x)
    acc = float(x[0])
    prev_t, prev_x = float(t[0]), float(x[0])
    for i, (ti, xi) in enumerate(zip(t.tolist(), x.tolist())):
        dt = ti - prev_t
        if dt > 0:
            k_tau = (xi - prev_x) / dt * tau_s
            acc = xi - k_tau + np.exp(-dt / tau_s) * (acc - prev_x + k_tau)
        y[i] = acc
        prev_t, prev_x = ti, xi
    return y


def centred_slope(t: np.ndarray, x: np.ndarray, window_s: float = RATE_WINDOW_S) -> np.ndarray:
    """Least-squares slope of x over t within +-window/2 of each sample, in units of x per minute."""
    lo = np.searchsorted(t, t - window_s / 2, side="left")
    hi = np.searchsorted(t, t + window_s / 2, side="right")
    tc = t - t[0]
    c1 = np.concatenate([[0.0], np.cumsum(tc)])
    c2 = np.concatenate([[0.0], np.cumsum(tc * tc)])
    cx = np.concatenate([[0.0], np.cumsum(x)])
    ctx = np.concatenate([[0.0], np.cumsum(tc * x)])
    n = (hi - lo).astype(float)
    st, stt = c1[hi] - c1[lo], c2[hi] - c2[lo]
    sx, stx = cx[hi] - cx[lo], ctx[hi] - ctx[lo]
    den = n * stt - st * st
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(den > 0, (n * stx - st * sx) / np.where(den > 0, den, 1.0), 0.0)
    return slope * 60.0


def relay_on_rate(rate: np.ndarray, threshold: float) -> np.ndarray:
    """+1 once heating faster than the threshold, -1 once cooling faster; holds in between."""
    out = np.empty_like(rate)
    state = 0.0
    for i, r in enumerate(rate.tolist()):
        if r > threshold:
            state = 1.0
        elif r < -threshold:
            state = -1.0
        out[i] = state
    return out


def play_operator(x: np.ndarray, width: float) -> np.ndarray:
    """Backlash (play) of a total width: the output follows x only once x has moved half the width
    past it.  Returns (play(x) - x): a memory that saturates at -+width/2 while heating/cooling."""
    half = width / 2.0
    out = np.empty_like(x)
    y = float(x[0])
    for i, xi in enumerate(x.tolist()):
        if y < xi - half:
            y = xi - half
        elif y > xi + half:
            y = xi + half
        out[i] = y - xi
    return out


def reversal_trigger(x: np.ndarray, band: float) -> np.ndarray:
    """Schmitt trigger on the direction of x: flips to +1 when x has risen ``band`` above its last
    minimum, to -1 when it has fallen ``band`` below its last maximum (abrupt memory)."""
    out = np.empty_like(x)
    state = 0.0
    lo = hi = float(x[0])
    for i, xi in enumerate(x.tolist()):
        lo, hi = min(lo, xi), max(hi, xi)
        if state <= 0 and xi > lo + band:
            state, hi = 1.0, xi
        elif state >= 0 and xi < hi - band:
            state, lo = -1.0, xi
        out[i] = state
    return out


def warmup(t: np.ndarray, power_on_s: list[float], tau_s: float) -> np.ndarray:
    """exp(-(t - t_on)/tau) after the latest power-on (0 before the first one)."""
    out = np.zeros_like(t)
    for on in sorted(power_on_s):
        after = t >= on
        out[after] = np.exp(-(t[after] - on) / tau_s)
    return out


# kind -> (function of (Signals, params), probes the effect depends on)
def _lag(s: Signals, p: dict) -> np.ndarray:
    return lag_irregular(s.t, s.temp(p["probe"]), p["tau_s"])


def _gradient(s: Signals, p: dict) -> np.ndarray:
    a, b = p["pair"]
    return s.temp(a) - s.temp(b)


def _rate(s: Signals, p: dict) -> np.ndarray:
    return s.rate(p["probe"])


def _temp_rate(s: Signals, p: dict) -> np.ndarray:
    return (s.temp(p["probe"]) - T_REF_C) * s.rate(p["probe"])


def _relay(s: Signals, p: dict) -> np.ndarray:
    return relay_on_rate(s.rate(p["probe"]), p["threshold_c_per_min"])


def _play(s: Signals, p: dict) -> np.ndarray:
    return play_operator(s.temp(p["probe"]), p["width_c"])


def _reversal(s: Signals, p: dict) -> np.ndarray:
    return reversal_trigger(s.temp(p["probe"]), p["band_c"])


def _warmup(s: Signals, p: dict) -> np.ndarray:
    return warmup(s.t, s.power_on_s, p["tau_s"])


def _drift(s: Signals, p: dict) -> np.ndarray:
    return (s.t - s.t[0]) / 3600.0


LIBRARY: dict[str, Callable[[Signals, dict], np.ndarray]] = {
    "lag": _lag,
    "gradient": _gradient,
    "rate": _rate,
    "temp_rate": _temp_rate,
    "hysteresis_relay": _relay,
    "hysteresis_play": _play,
    "hysteresis_reversal": _reversal,
    "warmup": _warmup,
    "drift": _drift,
}

# drivers that no column records: the generator adds a series, the oracle cannot rebuild it
UNRECORDED = ("humidity", "heater", "bias_step", "hvac")

# the product's names for each truth family (matched by substring on its effect kind)
FAMILY = {
    "lag": "lag",
    "gradient": "gradient",
    "rate": "rate",
    "temp_rate": "temp_rate",
    "hysteresis_relay": "hysteresis",
    "hysteresis_play": "hysteresis",
    "hysteresis_reversal": "hysteresis",
    "warmup": "warmup",
    "drift": "drift",
}


def probes_of(kind: str, params: dict) -> tuple[str, ...]:
    if kind == "gradient":
        return tuple(params["pair"])
    if "probe" in params:
        return (params["probe"],)
    return ()


def regressor(kind: str, params: dict, sig: Signals) -> np.ndarray:
    return LIBRARY[kind](sig, params)

"""The library of candidate physical effects tested against a calibration residual.

Each effect kind turns a dataset into one or more regressor columns, optionally for a value of a
nonlinear parameter (a time constant, a threshold) that the close-loop search scans.  The kinds and
the signature each one explains (calibration-notes section 3):

``thermal_lag``              bias follows a probe temperature through a first-order lag tau: the cubic
                             f(T_lag) replaces f(T): columns (T_lag - t0)^j - (T - t0)^j, j = 1..3
``gradient``                 a temperature difference between two probes (T_a - T_b)
``rate``                     dT/dt of a probe (C/min)
``rate_squared``             (dT/dt)^2
``temp_rate_cross``          (T - t0) * dT/dt
``hysteresis``               heating vs cooling: a relay state +1 after heating, -1 after cooling
                             (switches when |dT/dt| exceeds a threshold, holds otherwise)
``warmup``                   exp(-t_on / tau) with t_on the time since the last power-on
``g_sensitivity``            gravity projection on the body axes from the orientation column
``scale_factor_temperature`` input rate (Earth rate along the channel + table rate) x (T - t0)
``cross_channel_temperature`` another channel's temperature, cubic about t0 (the other channel's
                             thermal bias coupled in through misalignment)
``time_drift``               hours since the start of the run

All functions are pure: arrays in, arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import permutations
from typing import Callable

import numpy as np
from scipy.signal import lfilter

from bench.fit import prep
from bench.fit.base import Dataset

T0_C = 25.0
LAG_TAUS_S = (60.0, 120.0, 240.0, 480.0, 900.0, 1800.0, 3600.0, 7200.0)
WARMUP_TAUS_S = (60.0, 150.0, 300.0, 600.0, 1200.0, 2400.0, 4800.0)
HYSTERESIS_THRESHOLDS = (0.02, 0.05, 0.1, 0.2)   # C/min


@dataclass(frozen=True)
class Context:
    """What the effect generators need to know besides the data."""

    channel: str                      # e.g. "x"
    primary_probe: str                # the temperature name the declared model is built on
    probes: tuple[str, ...]           # all temperature names in the data
    channels: tuple[str, ...]         # all gyro channels in the data
    latitude_deg: float | None
    rate_window_s: float = 300.0


@dataclass
class Candidate:
    kind: str
    params: dict[str, float | str]
    build: Callable[[Dataset], dict[str, np.ndarray]]
    n_nonlinear: int = 0              # number of searched nonlinear parameters (BIC penalty)
    label: str = field(default="")
    # for a searched time constant: rebuild this candidate at another tau (grid refinement)
    at_tau: Callable[[float], "Candidate"] | None = None


# --------------------------------------------------------------------------------------------
# signal helpers

def sample_period(time_s: np.ndarray) -> float:
    if len(time_s) < 2:
        return 1.0
    return float(np.median(np.diff(time_s)))


def first_order_lag(x: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Output of a first-order lag (time constant tau) driven by x, started at x[0].

    Exact discretisation for a uniform sample period (the median period of the data)."""
    dt = sample_period(time_s)
    a = np.exp(-dt / tau_s)
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    return y


def rate_c_per_min(temp: np.ndarray, time_s: np.ndarray, window_s: float = 300.0) -> np.ndarray:
    """dT/dt in C/min, the fitting module's one definition (``prep.rate_c_per_min``); NaN -> 0 at the
    edges so a regressor column stays usable."""
    return np.nan_to_num(prep.rate_c_per_min(time_s, temp, window_s), nan=0.0)


def relay_state(rate: np.ndarray, threshold: float) -> np.ndarray:
    """+1 after heating faster than threshold, -1 after cooling faster than it; holds in between."""
    state = np.zeros_like(rate)
    on = np.where(rate > threshold, 1.0, np.where(rate < -threshold, -1.0, np.nan))
    # forward fill the last decided state; before any decision: 0
    idx = np.where(~np.isnan(on), np.arange(len(on)), 0)
    np.maximum.accumulate(idx, out=idx)
    state = on[idx]
    state[np.isnan(state)] = 0.0
    return state


def time_since_power_on(ds: Dataset) -> np.ndarray:
    """Seconds since the last 0->1 transition of ``power`` (since the start if no power column);
    NaN while the power is off."""
    t = ds.time
    if "power" not in ds:
        return t - t[0]
    power = np.nan_to_num(ds["power"], nan=0.0) > 0.5
    starts = np.where(power & np.concatenate([[True], ~power[:-1]]), t, np.nan)
    idx = np.where(~np.isnan(starts), np.arange(len(t)), 0)
    np.maximum.accumulate(idx, out=idx)
    since = t - starts[idx]
    since[~power] = np.nan
    return since


def body_axes_enu(orientation: np.ndarray) -> np.ndarray:
    """Array (n, 3, 3): [k, i, :] = direction of body axis i (x, y, z) in East-North-Up."""
    codes = np.asarray(orientation, dtype=object)
    codes = np.where(codes == "", prep.ORIENTATION_DEFAULT, codes)
    uniq, inverse = np.unique(codes, return_inverse=True)
    table = np.array([prep.orientation_axes(str(code)) for code in uniq])
    return table[inverse]


def _orientation(ds: Dataset) -> np.ndarray:
    if "orientation" in ds:
        return ds["orientation"]
    return np.full(len(ds), prep.ORIENTATION_DEFAULT, dtype=object)


# --------------------------------------------------------------------------------------------
# the library

def candidates(ctx: Context, ds: Dataset) -> list[Candidate]:
    """Every (kind, parameter) candidate applicable to this data."""
    out: list[Candidate] = []
    p = ctx.primary_probe
    w = ctx.rate_window_s
    tcol = lambda name: f"temp_{name}"  # noqa: E731

    def rate_of(d: Dataset, name: str) -> np.ndarray:
        return rate_c_per_min(d[tcol(name)], d.time, w)

    def lag_candidate(tau: float) -> Candidate:
        def lag(d):
            u = d[tcol(p)] - T0_C
            v = first_order_lag(d[tcol(p)], d.time, tau) - T0_C
            name = f"lag{tau:.0f}({p})"
            return {f"({name}-25)^{j}-({p}-25)^{j}": v ** j - u ** j for j in (1, 2, 3)}
        # the declared model's own temperature, lagged (a lag towards another probe is a gradient)
        return _labelled(Candidate("thermal_lag", {"probe": p, "tau_s": round(tau, 1)}, lag, 1, at_tau=lag_candidate))

    out.extend(lag_candidate(tau) for tau in LAG_TAUS_S)

    for a, b in permutations(ctx.probes, 2):
        if a < b:
            out.append(Candidate("gradient", {"probes": f"{a}-{b}"},
                                 lambda d, a=a, b=b: {f"({a}-{b})": d[tcol(a)] - d[tcol(b)]}))

    for probe in ctx.probes:
        out.append(Candidate("rate", {"probe": probe},
                             lambda d, probe=probe: {f"d{probe}": rate_of(d, probe)}))
        out.append(Candidate("rate_squared", {"probe": probe},
                             lambda d, probe=probe: {f"d{probe}^2": rate_of(d, probe) ** 2}))
        out.append(Candidate("temp_rate_cross", {"probe": probe},
                             lambda d, probe=probe: {f"({probe}-25)*d{probe}":
                                                     (d[tcol(probe)] - T0_C) * rate_of(d, probe)}))

    for thr in HYSTERESIS_THRESHOLDS:
        out.append(Candidate("hysteresis", {"probe": p, "threshold_c_per_min": thr},
                             lambda d, thr=thr: {f"relay{thr}(d{p})": relay_state(rate_of(d, p), thr)}, 1))

    if "power" in ds:
        def warmup_candidate(tau: float) -> Candidate:
            def warm(d):
                since = time_since_power_on(d)
                return {f"exp(-t_on/{tau:.0f})": np.nan_to_num(np.exp(-since / tau), nan=0.0)}
            return _labelled(Candidate("warmup", {"tau_s": round(tau, 1)}, warm, 1, at_tau=warmup_candidate))

        out.extend(warmup_candidate(tau) for tau in WARMUP_TAUS_S)

    if "orientation" in ds and len(np.unique(ds["orientation"])) > 1:
        def gravity(d):
            up = body_axes_enu(_orientation(d))[:, :, 2]       # up component of each body axis
            return {f"g_{ax}": up[:, i] for i, ax in enumerate("xyz")}
        out.append(Candidate("g_sensitivity", {}, gravity))

    if ctx.latitude_deg is not None or "table_rate_dps" in ds:
        def sf(d):
            w_in = np.zeros(len(d))
            if ctx.latitude_deg is not None:
                w_in = w_in + prep.earth_rate_reading(d, ctx.channel, ctx.latitude_deg)
            if "table_rate_dps" in d:
                w_in = w_in + np.nan_to_num(d["table_rate_dps"]) * 3600.0
            return {f"w_in*({p}-25)": w_in * (d[tcol(p)] - T0_C)}
        out.append(Candidate("scale_factor_temperature", {"probe": p}, sf))

    for other in _other_channel_temperatures(ctx):
        def cross(d, other=other):
            u = d[tcol(other)] - T0_C
            return {f"({other}-25)": u, f"({other}-25)^2": u ** 2, f"({other}-25)^3": u ** 3}
        out.append(Candidate("cross_channel_temperature", {"probe": other}, cross))

    out.append(Candidate("time_drift", {}, lambda d: {"t_hours": (d.time - d.time[0]) / 3600.0}))
    return [_labelled(c) for c in out]


def _labelled(c: Candidate) -> Candidate:
    c.label = c.kind + "(" + ", ".join(f"{k}={v}" for k, v in c.params.items()) + ")"
    return c


def _other_channel_temperatures(ctx: Context) -> list[str]:
    """Temperatures that belong to other channels: ``temp_<other channel>`` (e.g. ``temp_y`` while
    fitting ``gyro_x``).  Probes not tied to a channel are covered by ``gradient`` instead."""
    channel_names = set(ctx.channels) | {"x", "y", "z"}
    return [c for c in ctx.probes if c in channel_names and c != ctx.channel and c != ctx.primary_probe]


KINDS = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "hysteresis", "warmup",
         "g_sensitivity", "scale_factor_temperature", "cross_channel_temperature", "time_drift")

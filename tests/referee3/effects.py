"""The referee's own forms of the hidden effects, evaluated on temperatures given by name.

The same function serves the truth (probe die temperatures, before offset and quantisation) and the
oracle (what the probes recorded): ``column(effect, temps, t_s, power, hidden, dt)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import uniform_filter1d

from tests.referee3.physics import lowpass, play, relay

T_REF_C = 20.0

# kinds whose effect is a function of recorded columns (the product's library can name them)
LIBRARY_KINDS = ("lag", "gradient", "rate", "rate_squared", "temp_rate", "relay", "play", "warmup",
                 "time_drift")
# kinds driven by a variable no column records
UNRECORDED_KINDS = ("humidity", "internal_node", "mode_hop")


@dataclass
class Effect:
    kind: str
    probes: tuple[str, ...] = ()
    params: dict = field(default_factory=dict)
    coef: float = 1.0

    def describe(self) -> str:
        p = ",".join(self.probes)
        extra = ",".join(f"{k}={v:.4g}" for k, v in self.params.items())
        return f"{self.kind}({p}{';' if p and extra else ''}{extra})"


def rate_c_per_min(x: np.ndarray, dt: float, smooth_s: float = 120.0) -> np.ndarray:
    """dT/dt in C/min after a centred moving average of ``smooth_s`` (quantised readings need it)."""
    n = max(1, int(round(smooth_s / dt)))
    xs = uniform_filter1d(x, n, mode="nearest") if n > 1 else x
    return np.gradient(xs, dt) * 60.0


def time_since_power_on(t_s: np.ndarray, power: np.ndarray) -> np.ndarray:
    """Seconds since the last 0 -> 1 transition of ``power`` (since the start if it starts on)."""
    out = np.empty_like(t_s)
    t_on = t_s[0]
    prev = 0.0
    for k in range(t_s.size):
        p = power[k]
        if p >= 0.5 and prev < 0.5:
            t_on = t_s[k]
        prev = p
        out[k] = t_s[k] - t_on
    return out


def column(e: Effect, temps: dict[str, np.ndarray], t_s: np.ndarray, power: np.ndarray,
           hidden: dict[str, np.ndarray], dt: float) -> np.ndarray:
    """The effect's unit-coefficient regressor."""
    k = e.kind
    if k == "lag":
        return lowpass(temps[e.probes[0]], e.params["tau_s"], dt)
    if k == "gradient":
        return temps[e.probes[0]] - temps[e.probes[1]]
    if k == "rate":
        return rate_c_per_min(temps[e.probes[0]], dt)
    if k == "rate_squared":
        return rate_c_per_min(temps[e.probes[0]], dt) ** 2
    if k == "temp_rate":
        x = temps[e.probes[0]]
        return (x - T_REF_C) * rate_c_per_min(x, dt)
    if k == "relay":
        x = lowpass(temps[e.probes[0]], 60.0, dt)   # the relay sees the smoothed temperature
        return relay(x, e.params["width_c"])
    if k == "play":
        x = lowpass(temps[e.probes[0]], 60.0, dt)
        return x - play(x, e.params["width_c"])
    if k == "warmup":
        return np.exp(-time_since_power_on(t_s, power) / e.params["tau_s"])
    if k == "time_drift":
        return t_s / 3600.0
    if k in UNRECORDED_KINDS:
        return hidden[k]
    if k == "own_rate":      # a declared dynamic term, never hidden
        return rate_c_per_min(temps[e.probes[0]], dt)
    raise ValueError(f"unknown effect kind {k!r}")

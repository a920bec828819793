"""The true effects the corpus hides in a gyro's bias, each in two forms:

* ``signal(run)``: the physical contribution (before scaling) computed from the run's TRUE state
  (node temperatures of the thermal network, time since power-on, orientation, hidden variables);
* ``oracle(ds, hidden)``: the same effect in its true functional form with its true nonlinear
  parameters, computed from what the data records (measured, quantised probes; power; orientation),
  as regressor columns for the referee's "model with the true effects".  Effects driven by a variable
  no column records (``explainable = False``) take it from ``hidden`` (the referee only reports them).

Kinds use the product's names (thermal_lag, gradient, rate, rate_squared, temp_rate_cross,
hysteresis, warmup, g_sensitivity, scale_factor_temperature, time_drift); the unrecorded ones are
named for what they are (humidity, internal_node, mode_hop, bias_step).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bench.fit.base import Dataset
from tests.corpus import physics as ph

RATE_WINDOW_S = 300.0
T0_C = 25.0


@dataclass
class RunState:
    """The true state of one simulated run (what the generator knows and the data only partly shows)."""

    time_s: np.ndarray
    nodes: dict[str, np.ndarray]              # true node temperatures (C)
    power: np.ndarray                         # 0/1
    t_on_s: np.ndarray                        # seconds since the last power-on (NaN while off)
    orientation: np.ndarray                   # codes per sample
    table_rate_dps: np.ndarray
    latitude_deg: float
    probe_nodes: dict[str, str]               # probe name -> the node it is glued on
    hidden: dict[str, np.ndarray] = field(default_factory=dict)   # unrecorded variables

    def temp(self, probe: str) -> np.ndarray:
        """True temperature of the node the probe is glued on."""
        return self.nodes[self.probe_nodes[probe]]


def _rate(x: np.ndarray) -> np.ndarray:
    return np.gradient(x) * 60.0


def _probe(ds: Dataset, probe: str) -> np.ndarray:
    return np.asarray(ds[f"temp_{probe}"], dtype=float)


@dataclass
class Effect:
    kind: str
    probes: tuple[str, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)
    explainable: bool = True

    def signal(self, run: RunState, channel: str) -> np.ndarray:
        raise NotImplementedError

    def oracle(self, ds: Dataset, hidden: dict[str, np.ndarray], channel: str) -> np.ndarray:
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "probes": list(self.probes), "params": dict(self.params),
                "explainable": self.explainable}


class ThermalLag(Effect):
    """The sensing element follows the probe's node through a first-order lag (an internal gradient
    across a thermal resistance): contribution lag_tau(T) - T."""

    def __init__(self, probe: str, tau_s: float):
        super().__init__("thermal_lag", (probe,), {"tau_s": tau_s})

    def signal(self, run, channel):
        t = run.temp(self.probes[0])
        return ph.lag(t, self.params["tau_s"]) - t

    def oracle(self, ds, hidden, channel):
        t = _probe(ds, self.probes[0])
        return (ph.lag(t, self.params["tau_s"]) - t)[:, None]


class Gradient(Effect):
    def __init__(self, a: str, b: str):
        super().__init__("gradient", (a, b))

    def signal(self, run, channel):
        return run.temp(self.probes[0]) - run.temp(self.probes[1])

    def oracle(self, ds, hidden, channel):
        return (_probe(ds, self.probes[0]) - _probe(ds, self.probes[1]))[:, None]


class Rate(Effect):
    def __init__(self, probe: str):
        super().__init__("rate", (probe,))

    def signal(self, run, channel):
        return _rate(run.temp(self.probes[0]))

    def oracle(self, ds, hidden, channel):
        return ph.slope_c_per_min(_probe(ds, self.probes[0]), RATE_WINDOW_S)[:, None]


class RateSquared(Effect):
    def __init__(self, probe: str):
        super().__init__("rate_squared", (probe,))

    def signal(self, run, channel):
        return _rate(run.temp(self.probes[0])) ** 2

    def oracle(self, ds, hidden, channel):
        return (ph.slope_c_per_min(_probe(ds, self.probes[0]), RATE_WINDOW_S) ** 2)[:, None]


class TempRateCross(Effect):
    def __init__(self, probe: str):
        super().__init__("temp_rate_cross", (probe,))

    def signal(self, run, channel):
        t = run.temp(self.probes[0])
        return (t - T0_C) * _rate(t)

    def oracle(self, ds, hidden, channel):
        t = _probe(ds, self.probes[0])
        return ((t - T0_C) * ph.slope_c_per_min(t, RATE_WINDOW_S))[:, None]


class Hysteresis(Effect):
    """Duhem-like memory of the temperature path of the probe's node (``width_c`` of travel to
    saturate): a small width is relay-like, a large one gradual."""

    def __init__(self, probe: str, width_c: float):
        super().__init__("hysteresis", (probe,), {"width_c": width_c})

    def signal(self, run, channel):
        return ph.duhem(run.temp(self.probes[0]), self.params["width_c"])

    def oracle(self, ds, hidden, channel):
        smooth = ph.moving_average(_probe(ds, self.probes[0]), 120.0)
        return ph.duhem(smooth, self.params["width_c"])[:, None]


class Warmup(Effect):
    def __init__(self, tau_s: float):
        super().__init__("warmup", (), {"tau_s": tau_s})

    def signal(self, run, channel):
        return np.nan_to_num(np.exp(-run.t_on_s / self.params["tau_s"]), nan=0.0)

    def oracle(self, ds, hidden, channel):
        return np.nan_to_num(np.exp(-time_since_power_on(ds) / self.params["tau_s"]), nan=0.0)[:, None]


class GSensitivity(Effect):
    """Bias proportional to gravity along the body axes (three coefficients, one per axis)."""

    def __init__(self, per_axis: np.ndarray):
        super().__init__("g_sensitivity", (), {"per_axis": [float(v) for v in per_axis]})

    def signal(self, run, channel):
        return ph.gravity_up_body(run.orientation) @ np.asarray(self.params["per_axis"])

    def oracle(self, ds, hidden, channel):
        return ph.gravity_up_body(_orientation(ds))


class ScaleFactorTemperature(Effect):
    """Scale factor changing linearly with the coil temperature, seen through the input rate
    (table rate + Earth rate along the channel)."""

    def __init__(self, probe: str):
        super().__init__("scale_factor_temperature", (probe,))

    def signal(self, run, channel):
        w_in = input_rate_dph(run.table_rate_dps, run.orientation, run.latitude_deg, channel)
        return w_in * (run.temp(self.probes[0]) - T0_C)

    def oracle(self, ds, hidden, channel):
        table = np.asarray(ds["table_rate_dps"]) if "table_rate_dps" in ds else np.zeros(len(ds))
        w_in = input_rate_dph(table, _orientation(ds), float(ds.meta["latitude_deg"]), channel)
        return (w_in * (_probe(ds, self.probes[0]) - T0_C))[:, None]


class TimeDrift(Effect):
    def __init__(self):
        super().__init__("time_drift")

    def signal(self, run, channel):
        return (run.time_s - run.time_s[0]) / 3600.0

    def oracle(self, ds, hidden, channel):
        return ((ds.time - ds.time[0]) / 3600.0)[:, None]


class _Unrecorded(Effect):
    """Bias driven by a hidden quantity (``column`` of the run's hidden state) that no column records."""

    kind_name: str
    column: str

    def __init__(self):
        super().__init__(self.kind_name, explainable=False)

    def signal(self, run, channel):
        return run.hidden[self.column]

    def oracle(self, ds, hidden, channel):
        return hidden[self.kind][:, None]


class Humidity(_Unrecorded):
    """Bias driven by the relative humidity, which no column records."""

    kind_name, column = "humidity", "humidity_pct"


class InternalNode(_Unrecorded):
    """Bias driven by the self-heating of the electronics board: an internal node without a probe,
    heated by a load that changes and that no column records."""

    kind_name, column = "internal_node", "board_self_heating_c"


class BiasStep(_Unrecorded):
    """A step in the bias at a random time of each run, not driven by temperature (a shock, a contact
    settling): nothing recorded explains it."""

    kind_name, column = "bias_step", "bias_step"


class ModeHop(Effect):
    """A step in the bias when the coil crosses a temperature threshold (with a small dead band):
    a mode hop no column records."""

    def __init__(self, probe: str, threshold_c: float, band_c: float):
        super().__init__("mode_hop", (probe,), {"threshold_c": threshold_c, "band_c": band_c},
                         explainable=False)

    def signal(self, run, channel):
        t = run.temp(self.probes[0])
        return mode_state(t, self.params["threshold_c"], self.params["band_c"])

    def oracle(self, ds, hidden, channel):
        return hidden[self.kind][:, None]


def mode_state(temp: np.ndarray, threshold: float, band: float) -> np.ndarray:
    up = temp > threshold + band / 2
    down = temp < threshold - band / 2
    decided = np.where(up, 1.0, np.where(down, 0.0, np.nan))
    idx = np.where(np.isfinite(decided), np.arange(len(temp)), 0)
    np.maximum.accumulate(idx, out=idx)
    state = decided[idx]
    if np.isnan(state[0]):
        state[np.isnan(state)] = float(temp[0] > threshold)
    return state


# ---------------------------------------------------------------------------------------- helpers

def _orientation(ds: Dataset) -> np.ndarray:
    if "orientation" in ds:
        return np.asarray(ds["orientation"], dtype=object)
    return np.full(len(ds), "NUE", dtype=object)


def input_rate_dph(table_rate_dps: np.ndarray, orientation: np.ndarray, latitude_deg: float,
                   channel: str) -> np.ndarray:
    """True input rate along the channel: the table rate (its axis is aligned with the channel under
    test) plus the Earth rate along the channel's body axis."""
    i = "xyz".index(channel)
    return np.nan_to_num(table_rate_dps) * 3600.0 + ph.earth_rate_body(orientation, latitude_deg)[:, i]


def time_since_power_on(ds: Dataset) -> np.ndarray:
    t = ds.time
    if "power" not in ds:
        return t - t[0]
    on = np.nan_to_num(np.asarray(ds["power"], dtype=float)) > 0.5
    return since_on(t, on)


def since_on(t: np.ndarray, on: np.ndarray) -> np.ndarray:
    """Seconds since the last off->on transition (a run that starts on counts from its start); NaN
    while off."""
    starts = on & np.concatenate([[True], ~on[:-1]])
    idx = np.where(starts, np.arange(len(t)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = t - t[idx]
    out[~on] = np.nan
    return out

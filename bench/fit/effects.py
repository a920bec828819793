"""The library of candidate physical effects tested against a calibration residual.

Every effect is a *family*: a kind, the probe (or probe pair) it acts through, and at most one
continuous nonlinear parameter (a time constant, a threshold, a width) that the close-loop search
scans on a grid and refines (a hysteresis memory has a second one, its delay).  A family turns the run's ``Inputs`` into regressor columns.  The kinds
and the signature each one explains (calibration-notes section 3), each on EVERY probe:

``thermal_lag(probe, tau)``     the sensing element follows ``probe`` through a first-order lag tau:
                                the one column lag_tau(T_probe) - T_probe; and, on the declared
                                model's own probe, through the declared model's shape (form
                                "polynomial"): the one column f(lag_tau(T)) - f(T), f the declared
                                model's part in T as the training run fits it (``Context.own_shape``;
                                a more particular form of the linear lag, taken over it only on
                                strong evidence); on a probe still ramping when the training run
                                begins, its "unsettled" form adds the element's start offset there,
                                exp(-t / tau) (tau up to ``LAG_START_SPANS``), taken over the linear
                                lag only on strong evidence too
The declared model's own probe is the default: a family on another probe (or a pair) pays one more
searched parameter in the BIC.
``gradient(a-b)``               a temperature difference between two probes
``rate(probe, window)``         dT/dt of a probe (C/min), the derivative filter's window searched
``rate_squared(probe)``         (dT/dt)^2
``temp_rate_cross(probe)``      (T - T0) dT/dt, T0 the unit's own: the columns (T - 25) dT/dt and dT/dt
                                (a richer form of the rate, taken over it only on strong evidence)
``hysteresis(probe, relay)``    heating vs cooling: a relay state +1 after heating faster than a
                                threshold (C/min), -1 after cooling faster, held in between
``hysteresis(probe, reversal)`` a relay on the temperature path (a Schmitt trigger): +1 once the
                                temperature has risen a width (C) above its last minimum, -1 once it has
                                fallen a width below its last maximum
``hysteresis(probe, gradual)``  a memory that saturates over a temperature excursion, of two shapes:
                                Duhem, dm = (sign(dT) - m) |dT| / width, and play (backlash), which
                                moves one-for-one with T after a reversal and saturates after one width
The memories follow the probe's temperature path (``temperature_path``: readings' noise averaged out,
defined across recording outages), with a searched delay behind (or ahead of) the probe, and start from
a rule read off the run's own temperatures (``MEMORY_STARTS``).
``warmup(tau)``                 exp(-t_on / tau), t_on = time since the last power-on (since the start of
                                the run when no ``power`` column is recorded)
``g_sensitivity``               gravity projection on the body axes from the orientation column
``scale_factor_temperature``    input rate (Earth rate along the channel + table rate) x (T - 25)
``cross_channel_temperature``   another channel's temperature, cubic about 25 C
``time_drift``                  hours since the start of the run

All builders are pure functions of ``Inputs`` (arrays in, arrays out); ``Inputs`` can be the full-rate
run or its block means (the search runs on block means: the regressors are smooth).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from itertools import combinations
from typing import Any, Callable

import numpy as np

from bench.fit import prep
from bench.fit.base import Dataset
from bench.signal import BlockPlan, CentredSlopeRate, block_means, linear_recurrence, orientation_axes_per_sample, run_segments

T0_C = 25.0
LAG_TAUS_S = (60.0, 120.0, 240.0, 480.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
# a lag much shorter than a 100-s evidence block is a rate (lag_tau(T) - T = -tau dT/dt): the rate
# family names that, so the time constant is not refined below the grid's first value
LAG_LIMITS_S = (LAG_TAUS_S[0], 2.0 * LAG_TAUS_S[-1])
# a lag far slower than the record is within it the running integral of the temperature (a drift that
# follows the temperature history), not a time constant the data can tell: searched up to this many
# times the training run's length, and an optimum at that limit is not a lag (``Family.open_end``: on a
# run that starts at its warmest the integral is about linear in time, and such a lag had taken a time
# drift's place on TRAIN and then not generalised)
LAG_MAX_RUNS = 2.0
# a lagged element's state at a run's first row is history nothing recorded (the unit may have soaked
# elsewhere, or logging began mid-ramp): it starts where the probe's first reading puts it, off by an
# offset that decays as exp(-t / tau).  On the validation run it is estimated there (``closeloop``); on
# the training run the lag's unsettled form carries it as one more column (``Inputs.start_unknown``).
# Either is done for tau at most this fraction of the run's span (5 % left at its end): a slower
# element's offset is a trend of the run, not told from one
LAG_START_SPANS = 3.0
# the unsettled form of a lag is offered for a probe that is still ramping when the training run begins
# (its least-squares slope over the first ``START_RATE_WINDOW_S`` at least this, C/min): an element
# behind a ramp is off by about tau dT/dt, and one that just left a soak elsewhere by more.  Runs that
# begin settled (a soak drifts by hundredths of a C/min) give the lag no start to fit: offered there,
# the start column fitted a warm-up-like transient of other effects (held-out two effects 43, a
# gradient and a lag taken for one unsettled lag)
UNSETTLED_START_C_PER_MIN = 0.2
START_RATE_WINDOW_S = 600.0
# the lag of another probe's temperature itself (not minus it) differs from that temperature by about
# tau dT/dt: below three evidence blocks it is that probe's temperature (a gradient with the own
# probe) plus a small rate, which those families name
ABSOLUTE_LAG_MIN_S = 300.0
WARMUP_TAUS_S = (30.0, 60.0, 150.0, 300.0, 600.0, 1200.0, 2400.0, 4800.0, 9600.0)
RATE_WINDOWS_S = (60.0, 120.0, 300.0, 600.0, 1200.0)      # dT/dt filter windows (lesson 9)
RATE_WINDOW_PARAM = "window_s"    # the searched parameter of the rate effects: their filter's window
RELAY_THRESHOLDS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8)        # C/min
RELAY_WINDOWS_S = (60.0, 120.0, 300.0, 600.0)                   # the relay's rate filter
GRADUAL_WIDTHS_C = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)           # C
OPEN_END_SHARE = 0.95        # a parameter within 5 % of an open upper limit is at it (``Family.open_end``)


@dataclass(frozen=True)
class Context:
    """What the effect generators need to know besides the data."""

    channel: str                      # e.g. "x"
    primary_probe: str                # the temperature name the declared model is built on
    probes: tuple[str, ...]           # all temperature names in the data
    channels: tuple[str, ...]         # all gyro channels in the data
    latitude_deg: float | None
    rate_window_s: float = 300.0
    # the declared model's part in the primary probe alone, fitted on TRAIN: its coefficients of
    # (T - 25)^j, j = 1.. (empty: not known)
    own_shape: tuple[float, ...] = ()


@dataclass
class Inputs:
    """The physical inputs effects are built from, on one time grid (full rate or block means)."""

    time: np.ndarray
    temps: dict[str, np.ndarray]
    rates: dict[str, np.ndarray]            # C/min, NaN -> 0 at the edges
    since_on: np.ndarray                    # s since the last power-on (NaN while off)
    power_known: bool
    up: np.ndarray | None                   # (n, 3) up component of the body axes x, y, z
    input_rate: np.ndarray | None           # deg/h along the channel (Earth + table)
    paths: dict[str, np.ndarray] | None = None   # the temperature paths memories follow (``temperature_path``)
    # block means of ``source`` (the run at its own rate) over ``block_s``: a column that must be
    # computed at the readings' own rate (``relay``) is the block mean of the source's
    source: "Inputs | None" = field(default=None, repr=False)
    block_s: float | None = None
    # the run the coefficients are fitted on: its lags' start offsets are columns (``lag_start``); on any
    # other run those columns are zero (its own start is estimated on it, or left out)
    start_unknown: bool = False

    @property
    def dt(self) -> float:
        got = self.__dict__.get("_dt")
        if got is None:
            got = self.__dict__["_dt"] = sample_period(self.time)
        return got

    def rate(self, probe: str, window_s: float, near_gaps: str = "present") -> np.ndarray:
        """dT/dt (C/min) of a probe through a filter of ``window_s`` (``rate_c_per_min``; cached per
        window).  ``near_gaps="missing"``: NaN where the window reaches into a logger outage."""
        key = (probe, round(float(window_s), 3), near_gaps)
        cache = self.__dict__.setdefault("_rate_cache", {})
        got = cache.get(key)
        if got is None:
            if self.source is not None:
                # a derivative filter works on the readings: the block means of the source's rate (the
                # rate of block means would be a coarser filter, at least three blocks wide)
                got = cache[key] = self._from_source(self.source.rate(probe, window_s, near_gaps))
            else:
                slopes = self.__dict__.setdefault("_slope_cache", {})
                if probe not in slopes:
                    slopes[probe] = CentredSlopeRate(self.time, self.temps[probe])
                got = cache[key] = rate_c_per_min(self.temps[probe], self.time, max(float(window_s), 3 * self.dt),
                                                  near_gaps, slopes[probe])
        return got

    def own_rate(self, key: tuple, column: Callable[["Inputs"], np.ndarray]) -> np.ndarray:
        """``column`` of the run at the readings' own rate: on block means of a source, the block means
        of the source's column (a product of inputs averaged, not a product of averages; cached)."""
        if self.source is None:
            return column(self)
        cache = self.__dict__.setdefault("_own_rate_cache", {})
        got = cache.get(key)
        if got is None:
            got = cache[key] = self._from_source(column(self.source))
        return got

    def relay(self, probe: str, window_s: float, threshold: float) -> np.ndarray:
        """``relay_state`` of the probe's rate through a filter of ``window_s``.  On block means of a
        source run, the block means of the source's relay: a relay latches on the first crossing, which
        the readings' own noise brings forward; a rate of block means would switch later."""
        if self.source is not None:
            return self._from_source(self.source.relay(probe, window_s, threshold))
        return relay_state(self.rate(probe, window_s, near_gaps="missing"), threshold)

    def _from_source(self, values: np.ndarray) -> np.ndarray:
        """Block means of a source column over this grid's blocks (the plan built once)."""
        plan = self.__dict__.get("_plan")
        if plan is None:
            plan = self.__dict__["_plan"] = BlockPlan(self.source.time, self.block_s)
        return plan.means(values)

    def path(self, probe: str, delay_s: float = 0.0) -> np.ndarray:
        """The probe's temperature path as a hysteresis memory follows it (``temperature_path``): given
        at the run's own rate by ``build_inputs`` and averaged with the other inputs, computed here
        otherwise; as an element ``delay_s`` behind the probe follows it (``delayed_path``; cached)."""
        if self.paths is None:
            self.paths = {}
        got = self.paths.get(probe)
        if got is None:
            got = self.paths[probe] = temperature_path(self.time, self.temps[probe])
        if delay_s:
            key = (probe, round(float(delay_s), 1))
            cache = self.__dict__.setdefault("_delayed_paths", {})
            if key not in cache:
                cache[key] = delayed_path(self.time, got, key[1])
            got = cache[key]
        return got

    def __len__(self) -> int:
        return len(self.time)

    def averaged(self, block_s: float) -> "Inputs":
        """Block means over ``block_s`` seconds (``bench.signal.block_means``)."""
        if self.dt >= 0.9 * block_s:
            return self
        cols = {f"T:{k}": v for k, v in self.temps.items()}
        cols.update({f"R:{k}": v for k, v in self.rates.items()})
        cols.update({f"P:{k}": v for k, v in (self.paths or {}).items()})
        cols["since_on"] = self.since_on
        if self.up is not None:
            cols.update({f"up{i}": self.up[:, i] for i in range(3)})
        if self.input_rate is not None:
            cols["w_in"] = self.input_rate
        bm = block_means(self.time, cols, block_s)
        c = bm.columns
        return Inputs(time=bm.time_s, temps={k: c[f"T:{k}"] for k in self.temps},
                      rates={k: c[f"R:{k}"] for k in self.rates}, since_on=c["since_on"],
                      power_known=self.power_known,
                      up=None if self.up is None else np.column_stack([c[f"up{i}"] for i in range(3)]),
                      input_rate=c.get("w_in"), paths={k: c[f"P:{k}"] for k in (self.paths or {})},
                      source=self, block_s=float(block_s), start_unknown=self.start_unknown)


@dataclass(frozen=True)
class Family:
    """One effect family: kind + probe/pair (+ form), with its continuous parameter's grid."""

    kind: str
    fixed: tuple[tuple[str, str], ...]                       # e.g. (("probe", "t2"),)
    builder: Callable[[Inputs, float | None], dict[str, np.ndarray]]
    param: str | None = None                                 # name of the searched parameter
    grid: tuple[float, ...] = ()
    log_scale: bool = True
    chosen_probe: bool = True      # the probe/pair was searched (False: the declared model's own probe)
    options: int = 1               # how many probes / pairs it was chosen among
    limits: tuple[float, float] | None = None   # where the parameter stays meaningful (None: one grid
                                                # step beyond each end of the grid)
    variants: int = 1              # discrete variants of the family on one probe (a memory's start rules)
    # a memory's second searched parameter: the delay (s) of the temperature path it follows behind
    # the probe's (negative: ahead of it).  ``delayed`` families search it (and pay for it); the value
    # is part of the family, not of its identity (one memory per probe, form and start)
    delayed: bool = False
    delay_s: float = field(default=0.0, compare=False)
    # the columns change only where the parameter crosses a value the data reach (a relay's threshold,
    # a trigger's width): the training run pins it to an interval, not to a point
    stepwise: bool = False
    # the parameter's upper limit is where the effect stops being itself: a gradual memory as wide as
    # half the probe's span never saturates within the run, and its fit there is a drift along the
    # temperature's travel, not a hysteresis; a lag as slow as twice the record is the temperature's
    # running integral, a drift.  An optimum at that end is not this effect (``open_end``)
    open_above: bool = False
    # the simpler form of this effect (its kind and ``fixed``): its columns, with the declared model's,
    # lie within this one's (the cross term holds the rate), or this one is a particular case of it
    # (the lag through the declared model's shape); this one is taken over it only on strong evidence
    nests: tuple[str, tuple[tuple[str, str], ...]] | None = None

    def contains(self, other: "Family") -> bool:
        """This family is a richer form of ``other`` (``nests``)."""
        return self.nests is not None and (other.kind, other.fixed) == self.nests

    @property
    def bounds(self) -> tuple[float, float]:
        """The range the continuous parameter is refined in: the grid is only where the scan starts,
        an optimum at its edge is followed one grid step beyond it (or up to ``limits``)."""
        if self.limits is not None:
            return self.limits
        g = self.grid
        if len(g) < 2:
            return (g[0], g[0]) if g else (float("nan"), float("nan"))
        return (g[0] * g[0] / g[1], g[-1] * g[-1] / g[-2])

    def open_end(self, value: float | None) -> bool:
        """``value`` sits at the upper limit of a family whose upper limit is not the effect
        (``open_above``): the fit wants the parameter beyond where the effect is identified."""
        return bool(self.open_above and value is not None and value >= self.bounds[1] * OPEN_END_SHARE)

    @cached_property
    def label(self) -> str:
        """The family's name (its identity: a memory's delay is a searched value, in ``Effect.label``)."""
        return self.kind + "(" + ", ".join(f"{k}={v}" for k, v in self.fixed) + ")"

    def with_delay(self, delay_s: float) -> "Family":
        """The family with its memory's delay set (to the whole second: finer is beyond the data's
        timing, and the delay is part of an effect's label)."""
        return replace(self, delay_s=float(round(delay_s)))

    def penalty(self, n_eff: float) -> float:
        """BIC penalty of the family's searched parameters: ln(n_eff) for each continuous one (a
        memory's delay too), ln(number of options) for the probe or pair chosen among the data's (a
        discrete model choice; none for the declared model's own probe, whose variants, e.g. a memory's
        start rule, still count)."""
        pen = np.log(n_eff) * ((1 if self.param else 0) + (1 if self.delayed else 0))
        if self.fixed and self.chosen_probe and self.options > 1:
            pen += np.log(self.options)
        elif self.variants > 1:
            pen += np.log(self.variants)
        return float(pen)

    @property
    def n_nonlinear(self) -> int:
        """Searched nonlinear parameters, for the BIC penalty: the continuous one, and the probe or
        pair choice unless it is the declared model's own probe (the default, no choice made)."""
        return (1 if self.param else 0) + (1 if self.delayed else 0) + (1 if self.fixed and self.chosen_probe else 0)

    def at(self, value: float | None) -> "Effect":
        return Effect(self, None if value is None else float(value))

    @cached_property
    def grid_effects(self) -> tuple["Effect", ...]:
        """The effect at each value of the scan grid (a family without a parameter: its one effect),
        made once: the search scans a family's grid thousands of times, and an effect keeps its label."""
        return tuple(self.at(v) for v in self.grid) if self.grid else (self.at(None),)


@dataclass(frozen=True)
class Effect:
    family: Family
    value: float | None = None

    @property
    def kind(self) -> str:
        return self.family.kind

    @property
    def params(self) -> dict[str, float | str]:
        out: dict[str, float | str] = dict(self.family.fixed)
        if self.family.param:
            out[self.family.param] = _round(self.value)
        if self.family.delayed:
            out["delay_s"] = _round(self.family.delay_s)
        return out

    @cached_property
    def label(self) -> str:
        # cached: the search's column and projector caches are keyed by it, hundreds of thousands of times
        values = [f"{self.family.param}={_round(self.value)}"] if self.family.param else []
        if self.family.delayed:
            values.append(f"delay_s={_round(self.family.delay_s)}")
        return self.family.label + (f"[{', '.join(values)}]" if values else "")

    def columns(self, inputs: Inputs) -> dict[str, np.ndarray]:
        if self.family.delayed:
            return self.family.builder(inputs, self.value, self.family.delay_s)
        return self.family.builder(inputs, self.value)

    def with_value(self, value: float) -> "Effect":
        return replace(self, value=float(value))


def _round(v: float | None) -> float:
    if v is None:
        return float("nan")
    return float(f"{v:.3g}")


# --------------------------------------------------------------------------------------------
# signal helpers

def sample_period(time_s: np.ndarray) -> float:
    if len(time_s) < 2:
        return 1.0
    return float(np.median(np.diff(time_s)))


def first_order_lag(x: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Output of a first-order lag (time constant tau) driven by x, started in equilibrium at x[0],
    exact for an input that is linear between samples (the ramp-invariant step): with a = exp(-dt/tau)
    and c = (1 - a) tau / dt, y[i] = a y[i-1] + (1 - c) x[i] + (c - a) x[i-1], each sample's own dt.
    Over a logger outage the temperature went on changing between the readings either side of it: the
    lag relaxes for the outage's length towards that straight line (not towards the reading after it,
    held for the whole outage).  Missing input samples (failed conversions) are interpolated in time."""
    x = np.asarray(x, dtype=np.float64)
    t = np.asarray(time_s, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        x = _interpolate_missing(x, t)
    if len(x) == 0:
        return x.copy()
    dt = sample_period(t)
    steps = np.diff(t)
    if len(steps) and np.max(np.abs(steps - dt)) > 0.5 * dt:
        h = np.concatenate([[dt], steps])
        a = np.exp(-h / tau_s)
        c = -np.expm1(-h / tau_s) * tau_s / h
        x_prev = np.concatenate([[x[0]], x[:-1]])
        return linear_recurrence(a, (1.0 - c) * x + (c - a) * x_prev, float(x[0]))
    a = float(np.exp(-dt / tau_s))
    c = float(-np.expm1(-dt / tau_s) * tau_s / dt)
    from scipy.signal import lfilter   # scipy.signal takes seconds to import: only when used

    # the state of an input and output that stood at x[0] before the first sample
    zi = [a * x[0] + (c - a) * x[0]]
    y, _ = lfilter([1.0 - c, c - a], [1.0, -a], x, zi=zi)
    return y


def whole_power(x: np.ndarray, j: int) -> np.ndarray:
    """``x ** j`` for a whole ``j``, raised on ``|x|`` with the sign put back for an odd ``j``: numpy
    raises an array that holds a negative base element by element (measured: 60x slower on a probe's
    T - 25 below 25 C, the lag through the declared model's shape spent a tenth of the search there)."""
    a = np.abs(x) ** j
    return np.copysign(a, x) if j % 2 else a


def _interpolate_missing(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """NaN samples linearly interpolated in time between the readings either side (held at the ends);
    all zeros when nothing is present."""
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros_like(x)
    return np.interp(t, t[ok], x[ok])


def _hold_missing(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros_like(x)
    idx = np.where(ok, np.arange(len(x)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = x[idx]
    out[: int(np.argmax(ok))] = x[int(np.argmax(ok))]
    return out


def rate_c_per_min(temp: np.ndarray, time_s: np.ndarray, window_s: float = 300.0,
                   near_gaps: str = "present", slope: CentredSlopeRate | None = None) -> np.ndarray:
    """dT/dt in C/min (``bench.signal.temperature_rate``, centred slope, as the declared models' rate
    terms).  Beside a logger outage (``near_gaps="present"``) the slope of the readings present in the
    window: an element kept changing its temperature while the logger was off, its rate is not zero
    there; NaN -> 0 where even that is undefined, so a regressor column stays usable.  With
    ``near_gaps="missing"`` NaN stays NaN there (a relay holds its state: a one-sided slope beside an
    outage is too noisy to latch on; measured: a rate relay at 1.45x the oracle's error with it, 0.97x
    holding).  ``slope``: the record's ``CentredSlopeRate`` when it is kept for many windows."""
    rate = (slope or CentredSlopeRate(time_s, temp)).rate(window_s, near_gaps)
    return rate if near_gaps == "missing" else np.nan_to_num(rate, nan=0.0)


def relay_state(rate: np.ndarray, threshold: float) -> np.ndarray:
    """+1 after heating faster than threshold, -1 after cooling faster than it; holds in between
    (``threshold`` >= 0, as every relay family's scan grid and bounds are)."""
    rate = np.asarray(rate, dtype=np.float64)
    switched = np.abs(rate) > threshold           # NaN never switches: the state holds through it
    idx = np.where(switched, np.arange(len(rate)), 0)
    np.maximum.accumulate(idx, out=idx)           # the last switching sample up to each one
    return np.where(switched[idx], np.sign(rate[idx]), 0.0)


def duhem_state(rate_c_per_min_: np.ndarray, time_s: np.ndarray, width_c: float, start: float = 0.0) -> np.ndarray:
    """The Duhem memory (``duhem_memory``) driven by a rate: steps dT = rate x the median sample
    period."""
    return _duhem(np.nan_to_num(rate_c_per_min_) * sample_period(time_s) / 60.0, width_c, start)


def duhem_memory(path: np.ndarray, width_c: float, start: float = 0.0) -> np.ndarray:
    """Gradual (Duhem) hysteresis memory m in [-1, 1] driven by the changes dT of a temperature path
    (``temperature_path``): at each step m moves towards sign(dT) by the fraction 1 - exp(-|dT| / width),
    so it saturates after a one-way excursion of a few ``width_c`` and keeps its value during soaks; it
    starts at ``start``.  A step over a recording outage is the path's change across it: exact for a
    monotone outage (the memory depends only on the path's travel between its turning points)."""
    x = np.asarray(path, dtype=np.float64)
    return _duhem(np.diff(x, prepend=x[:1]), width_c, start)


def _duhem(steps_c: np.ndarray, width_c: float, start: float) -> np.ndarray:
    a = np.exp(-np.abs(steps_c) / width_c)
    return linear_recurrence(a, (1.0 - a) * np.sign(steps_c), float(start))


def play_memory(path: np.ndarray, width_c: float, start: float = 0.0) -> np.ndarray:
    """Gradual hysteresis of the play (backlash) form, a Prandtl-Ishlinskii cell: an internal position p
    follows the temperature path x only when x is more than half of ``width_c`` away from it; the memory
    m = (x - p) / (width_c / 2) in [-1, 1] moves one-for-one with x after a reversal and is saturated
    once x has travelled one width from it.  It starts at ``start`` (p = x0 - start x width/2).  Like
    every memory of the path it is defined across an outage by the path's change."""
    x = np.asarray(path, dtype=np.float64)
    h = width_c / 2.0
    if not len(x):
        return np.empty(0)
    return (x - _backlash(x, h, float(x[0]) - float(np.clip(start, -1.0, 1.0)) * h)) / h


def _backlash(x: np.ndarray, h: float, p0: float) -> np.ndarray:
    """The play operator's position: p follows x only when x is more than ``h`` away from it
    (p_i = x_i - h when x_i - h > p_{i-1}, x_i + h when x_i + h < p_{i-1}, else p_{i-1}).
    Computed a stretch at a time: while p is pushed up only it is the running maximum of x - h (and
    of its start), while pushed down only the running minimum of x + h; a stretch ends at the first
    push the other way (``_first_true`` grows its look-ahead, so a run costs O(n) array work plus a
    few array calls per reversal)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty(len(x))
    p, i, rising = float(p0), 0, True
    while i < len(x):
        def pushed_back(c: np.ndarray, p=p, rising=rising):
            run = np.maximum(p, np.maximum.accumulate(c - h)) if rising else np.minimum(p, np.minimum.accumulate(c + h))
            before = np.concatenate([[p], run[:-1]])
            return ((c + h < before) if rising else (c - h > before)), run
        k, run = _first_true(x, i, pushed_back)
        stop = len(x) if k is None else k
        out[i:stop] = run[:stop - i]
        if k is None:
            break
        p = float(x[k] + h) if rising else float(x[k] - h)
        out[k] = p
        i, rising = k + 1, not rising
    return out


def _first_true(x: np.ndarray, start: int, test: Callable[[np.ndarray], tuple[np.ndarray, Any]],
                first_look: int = 4096) -> tuple[int | None, Any]:
    """First index k >= start where ``test`` (a vectorised scan of x[start:...] returning a mask and the
    scanned values, both depending only on the samples up to each index) is true, and the scanned
    values from ``start`` up to k (to the end when never).  Looks ahead ``first_look`` samples, then
    twice as far each time nothing is found, rescanning from ``start``.  The answer does not depend on
    ``first_look``, only the cost: a look too short pays a call per doubling, one too long scans past
    the hit (measured on a 10-h run at 1 s, the relay and play memories over 5 widths and 3 starts:
    49 ms at 64 samples, 35 ms at 4096, 55 ms at 65536)."""
    look = first_look
    while True:
        end = min(len(x), start + look)
        mask, run = test(x[start:end])
        hit = np.flatnonzero(mask)
        if hit.size:
            return start + int(hit[0]), run
        if end == len(x):
            return None, run
        look *= 2


# A memory follows the temperature, not its readings: the readings' noise and quantisation steps are
# averaged out over PATH_SMOOTH_S (centred, within each stretch of the record), and what noise is left
# is held inside a dead band of PATH_BAND_SIGMAS standard deviations of that average, so that a soak
# moves no memory and a ramp moves it by the temperature's own change
PATH_SMOOTH_S = 60.0
PATH_BAND_SIGMAS = 8.0


def temperature_path(time_s: np.ndarray, temp: np.ndarray) -> np.ndarray:
    """The temperature path a hysteresis memory follows, from a probe's readings (C): missing readings
    interpolated, a centred mean over ``PATH_SMOOTH_S`` (shrinking symmetrically at the ends of each
    stretch, so a ramp is not bent), then a backlash (play) of the width of the averaged noise
    (``PATH_BAND_SIGMAS`` x its standard deviation, from the readings' scatter about the mean).
    Over a recording outage the path steps by the temperature's change across it."""
    t = np.asarray(time_s, dtype=np.float64)
    x = np.asarray(temp, dtype=np.float64)
    ok = np.isfinite(x)
    if ok.sum() < 2:
        return _hold_missing(x)
    x = _interpolate_missing(x, t)
    dt = sample_period(t)
    half = int(PATH_SMOOTH_S / dt / 2.0)
    if half < 1:
        return x
    smooth = np.empty_like(x)
    for seg in run_segments(t):
        smooth[seg] = _centred_mean(x[seg], half)
    # the readings' scatter about the mean: their standard deviation, the rarest 0.1 % left out (a
    # glitch must not widen the band; quantisation steps flipping now and then must count)
    resid = np.abs((x - smooth)[ok])
    sigma = float(np.sqrt(np.mean(np.square(resid[resid <= np.quantile(resid, 0.999)]))))
    band = PATH_BAND_SIGMAS * sigma / np.sqrt(2 * half + 1)
    if not band > 0:
        return smooth
    return _backlash(smooth, band / 2.0, float(smooth[0]))


def delayed_path(time_s: np.ndarray, path: np.ndarray, delay_s: float) -> np.ndarray:
    """The path as an element ``delay_s`` behind the probe follows it: through a first-order lag of
    that time constant (the element's own thermal path, as ``thermal_lag``); a negative delay is an
    element ahead of the probe (the probe's own lag behind it): the path that much earlier, held at
    the run's end."""
    if delay_s > 0:
        return first_order_lag(path, time_s, delay_s)
    return np.interp(time_s - delay_s, time_s, path)


def _centred_mean(x: np.ndarray, half: int) -> np.ndarray:
    """Mean over x[i - k .. i + k], k = min(half, i, n - 1 - i)."""
    n = len(x)
    c = np.concatenate([[0.0], np.cumsum(x - x[0])])
    i = np.arange(n)
    k = np.minimum(np.minimum(half, i), n - 1 - i)
    return (c[i + k + 1] - c[i - k]) / (2 * k + 1) + x[0]


# How a hysteresis memory starts a run.  Its state at power-on is set by the unit's history before the
# run, which no column records; each rule infers it from the run's own temperature path (never from
# the gyro), so the rule chosen on TRAIN applies unchanged to any other run:
#   "neutral"   half-way (0), no preference;
#   "reversed"  saturated on the branch the run's first excursion of one width reverses (the unit was
#               brought to the start temperature from the other side, as a soak before a ramp away
#               from it usually is);
#   "continued" saturated on the branch of that first excursion (approached from the same side).
MEMORY_STARTS = ("neutral", "reversed", "continued")
# The shapes of a gradual memory: "duhem" saturates exponentially over its width of travel
# (``duhem_memory``), "play" moves one-for-one with the temperature after a reversal and saturates
# sharply after one width (``play_memory``)
GRADUAL_SHAPES = ("duhem", "play")
# The delay of a memory's temperature path behind its probe's (s): the element that remembers follows
# the probe's temperature through its own thermal path (later; a probe behind the element: earlier).
# Scanned on this grid and refined between its points (``SearchProblem.best_value``), within the limits
MEMORY_DELAYS_S = tuple(float(d) for d in range(-300, 301, 30))
MEMORY_DELAY_LIMITS_S = (-600.0, 600.0)


def start_variants(effect: "Effect", families: list["Family"]) -> list["Effect"]:
    """The effect under each start rule of its memory (``MEMORY_STARTS``), its width and delay kept:
    the same family but for the start (itself first); [effect] for an effect without a start rule."""
    def identity(f: "Family") -> tuple:
        return f.kind, tuple(kv for kv in f.fixed if kv[0] != "start")

    own = identity(effect.family)
    out = [effect]
    for f in families:
        if identity(f) == own and f.label != effect.family.label:
            out.append(Effect(f.with_delay(effect.family.delay_s), effect.value))
    return out


def start_rule(effect: "Effect") -> str:
    """The start rule of a memory effect (``MEMORY_STARTS``; a gradual memory without one is neutral)."""
    return str(dict(effect.family.fixed).get("start", "neutral"))


def first_excursion_sign(temp: np.ndarray, width_c: float) -> float:
    """+1 / -1: the direction of the first move of at least ``width_c`` away from the start temperature
    (+1 when the run never moves that far)."""
    x = _hold_missing(np.asarray(temp, dtype=np.float64))
    moved = np.flatnonzero(np.abs(x - x[0]) >= width_c)
    return float(np.sign(x[moved[0]] - x[0])) if moved.size else 1.0


def memory_start(rule: str, temp: np.ndarray, width_c: float) -> float:
    """The memory's state at the start of a run under a start rule (``MEMORY_STARTS``)."""
    if rule == "neutral":
        return 0.0
    first = first_excursion_sign(temp, width_c)
    if rule == "reversed":
        return -first
    if rule == "continued":
        return first
    raise ValueError(f"unknown hysteresis start rule {rule!r}; expected one of {', '.join(MEMORY_STARTS)}")


def reversal_relay_state(temp: np.ndarray, width_c: float, start: float) -> np.ndarray:
    """Relay hysteresis on the temperature path (a Schmitt trigger on T): the state switches to +1
    once T has risen ``width_c`` above its lowest value since the last switch, to -1 once it has
    fallen ``width_c`` below its highest; it holds in between and starts at ``start`` (+1 or -1; 0:
    neither branch, until the first move of ``width_c`` away from the start).
    The sample in whose step the switching level is crossed takes the share of the step after the
    crossing (T linear within the step), so that the state's means move continuously with the width
    and the path's timing, however coarse the samples."""
    x = _hold_missing(np.asarray(temp, dtype=np.float64))
    out = np.empty(len(x))
    if not len(x):
        return out
    s, i = float(np.sign(start)), 0
    hi = lo = float(x[0])
    while i < len(x):
        def switch(c: np.ndarray, s=s, hi=hi, lo=lo):
            his = np.maximum(hi, np.maximum.accumulate(c))
            los = np.minimum(lo, np.minimum.accumulate(c))
            down = (his - c >= width_c) if s >= 0 else np.zeros(len(c), bool)
            up = (c - los >= width_c) if s <= 0 else np.zeros(len(c), bool)
            return down | up, (his, los, down)
        k, run = _first_true(x, i, switch)
        stop = len(x) if k is None else k
        out[i:stop] = s
        if k is None:
            break
        v, prev = float(x[k]), float(x[max(k - 1, 0)])
        hi, lo, down = (float(a[k - i]) for a in run)
        if down:
            level = hi - width_c
            after = (level - v) / (prev - v) if prev > v and prev > level else 1.0
            out[k], s, lo = s - (s + 1.0) * after, -1.0, v
        else:
            level = lo + width_c
            after = (v - level) / (v - prev) if v > prev and prev < level else 1.0
            out[k], s, hi = s + (1.0 - s) * after, 1.0, v
        i = k + 1
    return out


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
    return orientation_axes_per_sample(np.asarray(orientation, dtype=object))


def _varies(x: np.ndarray) -> bool:
    """True when ``x`` takes more than one value beyond floating-point rounding of its magnitude."""
    v = x[np.isfinite(x)]
    if len(v) < 2:
        return False
    return float(np.ptp(v)) > 1e-9 * max(1.0, float(np.max(np.abs(v))))


def build_inputs(ds: Dataset, ctx: Context, start_unknown: bool = False) -> Inputs:
    """The inputs of every effect, at the run's own rate (``start_unknown``: the run the coefficients are
    fitted on, ``Inputs.start_unknown``)."""
    t = np.asarray(ds.time, dtype=np.float64)
    temps = {p: np.asarray(ds[f"temp_{p}"], dtype=np.float64) for p in ctx.probes if f"temp_{p}" in ds}
    rates = {p: rate_c_per_min(v, t, ctx.rate_window_s) for p, v in temps.items()}
    up = None
    if "orientation" in ds and len(np.unique(ds["orientation"])) > 1:
        up = body_axes_enu(ds["orientation"])[:, :, 2]
    w_in = None
    if ctx.latitude_deg is not None or "table_rate_dps" in ds:
        w_in = np.zeros(len(t))
        if ctx.latitude_deg is not None:
            w_in = w_in + prep.earth_rate_reading(ds, ctx.channel, ctx.latitude_deg)
        if "table_rate_dps" in ds:
            w_in = w_in + np.nan_to_num(np.asarray(ds["table_rate_dps"], dtype=np.float64)) * 3600.0
    return Inputs(time=t, temps=temps, rates=rates, since_on=time_since_power_on(ds),
                  power_known="power" in ds, up=up, input_rate=w_in,
                  paths={p: temperature_path(t, v) for p, v in temps.items()}, start_unknown=start_unknown)


def start_rate(x: Inputs, probe: str) -> float:
    """The probe's least-squares slope (C/min) over the run's first ``START_RATE_WINDOW_S`` (0 without
    three readings there)."""
    t, v = x.time, x.temps[probe]
    ok = np.isfinite(v) & (t - t[0] <= START_RATE_WINDOW_S)
    if ok.sum() < 3 or np.ptp(t[ok]) <= 0:
        return 0.0
    return float(np.polyfit(t[ok] - t[0], v[ok], 1)[0] * 60.0)


def lag_start(x: Inputs, tau_s: float) -> np.ndarray:
    """The column of a lagged element's unknown start state: exp(-(t - t0) / tau) on the run the
    coefficients are fitted on (``Inputs.start_unknown``); zero on any other run."""
    if not x.start_unknown:
        return np.zeros(len(x.time))
    tau = max(1.0, float(tau_s))
    return x.own_rate(("lag start", round(tau, 3)), lambda s: np.exp(-(s.time - s.time[0]) / tau))


# --------------------------------------------------------------------------------------------
# the library

def families(ctx: Context, inputs: Inputs) -> list[Family]:
    """Every effect family applicable to these inputs."""
    out: list[Family] = []
    probes = [p for p in ctx.probes if p in inputs.temps]

    own = ctx.primary_probe
    duration = float(inputs.time[-1] - inputs.time[0]) if len(inputs) > 1 else 0.0
    lag_limits = (LAG_LIMITS_S[0], max(LAG_LIMITS_S[0], min(LAG_LIMITS_S[1], LAG_MAX_RUNS * duration)))
    lag_taus = tuple(t for t in LAG_TAUS_S if t <= lag_limits[1]) or LAG_TAUS_S[:1]
    # where the run's length sets the lag's upper limit (below the grid's own), a time constant there is
    # the running integral of the temperature, not a lag the run tells: an optimum at that end is not
    # this effect
    lag_open = lag_limits[1] < LAG_LIMITS_S[1]
    ramping = {p for p in probes if abs(start_rate(inputs, p)) >= UNSETTLED_START_C_PER_MIN}
    unsettled_limits = (lag_limits[0], min(lag_limits[1], duration / LAG_START_SPANS))
    unsettled_taus = tuple(t for t in lag_taus if t <= unsettled_limits[1])
    for p in probes:
        def lag_linear(x: Inputs, tau, p=p):
            # the element's first-order lag behind the probe: lag_tau(T_p) - T_p
            v = first_order_lag(x.temps[p], x.time, tau)
            return {f"lag{tau:.0f}({p})-{p}": v - x.temps[p]}
        out.append(Family("thermal_lag", (("probe", p),), lag_linear, "tau_s", lag_taus, chosen_probe=p != own,
                          limits=lag_limits, open_above=lag_open))

        def lag_unsettled(x: Inputs, tau, p=p, linear=lag_linear):
            # the same element away from the probe's first reading when the training run began (it had
            # soaked elsewhere, or logging began mid-ramp): its start offset, decaying, is a column too
            return {**linear(x, tau), f"start(lag{tau:.0f}({p}))": lag_start(x, tau)}
        # a richer form of the lag, taken over it only on strong evidence, for an element whose start
        # offset decays within the run: a slower one's is a trend of the run, not a start (offered at any
        # tau, a lag of another probe of 8.75 h with its start column had stood in for a rate of t2 on
        # TRAIN and was not the cause on VALIDATE: fifth referee rate 1)
        if p in ramping and unsettled_taus:
            out.append(Family("thermal_lag", (("probe", p), ("initial", "unsettled")), lag_unsettled, "tau_s",
                              unsettled_taus, chosen_probe=p != own, limits=unsettled_limits,
                              nests=("thermal_lag", (("probe", p),))))
        if p != own:
            def lag_absolute(x: Inputs, tau, p=p):
                # an element that follows another probe's node with a lag: its temperature lag_tau(T_p)
                # itself (the declared model holds the own probe, not T_p, so lag - T_p would impose
                # -1x T_p that nothing in the physics asks for)
                return {f"lag{tau:.0f}({p})-25": first_order_lag(x.temps[p], x.time, tau) - T0_C}
            # a faster element is the probe's own temperature (plus a rate): the gradient names that
            abs_limits = (ABSOLUTE_LAG_MIN_S, max(ABSOLUTE_LAG_MIN_S, lag_limits[1]))
            out.append(Family("thermal_lag", (("probe", p), ("form", "absolute")), lag_absolute, "tau_s",
                              tuple(t for t in lag_taus if t >= ABSOLUTE_LAG_MIN_S) or (ABSOLUTE_LAG_MIN_S,),
                              limits=abs_limits, open_above=lag_open))
    shape = tuple(float(c) for c in ctx.own_shape)
    if own in probes and any(c != 0.0 for c in shape[1:]):
        def lag_shape(x: Inputs, tau, p=own, c=shape):
            # the element follows the probe through a lag and the declared model holds at the element's
            # temperature: f(lag T) - f(T), f the declared model's part in T as TRAIN fitted it (one
            # column, its size searched: the same freedom as the linear lag, which it is for a linear f)
            def column(s: Inputs) -> np.ndarray:
                u = s.temps[p] - T0_C
                v = first_order_lag(s.temps[p], s.time, tau) - T0_C
                return sum(cj * (whole_power(v, j) - whole_power(u, j)) for j, cj in enumerate(c, 1))
            return {f"f(lag{tau:.0f}({p}))-f({p})": x.own_rate(("lag shape", p, round(float(tau), 3)), column)}
        # a more particular form of the linear lag of the own probe, taken over it only on strong evidence
        out.append(Family("thermal_lag", (("probe", own), ("form", "polynomial")), lag_shape, "tau_s", lag_taus,
                          chosen_probe=False, limits=lag_limits, open_above=lag_open,
                          nests=("thermal_lag", (("probe", own),))))

    for a, b in combinations(probes, 2):
        out.append(Family("gradient", (("probes", f"{a}-{b}"),),
                          lambda x, _v, a=a, b=b: {f"({a}-{b})": x.temps[a] - x.temps[b]}))

    for p in probes:
        mine = p != own
        out.append(Family("rate", (("probe", p),), lambda x, w, p=p: {f"d{p}[{w:.0f}s]": x.rate(p, w)},
                          RATE_WINDOW_PARAM, RATE_WINDOWS_S, chosen_probe=mine))
        if ctx.rate_window_s:
            # the same rate through the declared model's own filter: nothing searched but the probe (a
            # window the data barely pin pays a whole parameter and lost a true rate to a gradient
            # that fits it alike)
            w0 = float(ctx.rate_window_s)
            out.append(Family("rate", (("probe", p), ("form", "declared_window"), (RATE_WINDOW_PARAM, f"{w0:.0f}")),
                              lambda x, _v, p=p, w0=w0: {f"d{p}[{w0:.0f}s]": x.rate(p, w0)}, chosen_probe=mine))
        out.append(Family("rate_squared", (("probe", p),),
                          lambda x, w, p=p: {f"d{p}[{w:.0f}s]^2": x.own_rate(
                              ("rate^2", p, round(float(w), 3)), lambda s: s.rate(p, w) ** 2)},
                          RATE_WINDOW_PARAM, RATE_WINDOWS_S, chosen_probe=mine))
        # (T - T0) dT/dt with the unit's T0 unknown: (T - 25) dT/dt and dT/dt, both sized
        out.append(Family("temp_rate_cross", (("probe", p),),
                          lambda x, w, p=p: {f"({p}-25)*d{p}[{w:.0f}s]": x.own_rate(
                              ("temp*rate", p, round(float(w), 3)), lambda s: (s.temps[p] - T0_C) * s.rate(p, w)),
                              f"d{p}[{w:.0f}s]": x.rate(p, w)},
                          RATE_WINDOW_PARAM, RATE_WINDOWS_S, chosen_probe=mine, nests=("rate", (("probe", p),))))
        # the relay switches on the rate as the element sees it: its smoothing (the rate filter's
        # window) is the element's own, unknown, so each window is a variant of the relay
        for w in RELAY_WINDOWS_S:
            out.append(Family("hysteresis", (("probe", p), ("form", "relay"), ("window_s", f"{w:.0f}")),
                              lambda x, thr, p=p, w=w: {f"relay{thr:.3g}(d{p}[{w:.0f}s])": x.relay(p, w, thr)},
                              "threshold_c_per_min", RELAY_THRESHOLDS, chosen_probe=mine,
                              variants=len(RELAY_WINDOWS_S), stepwise=True))
        widths = _widths_for(inputs.temps[p])
        if widths:
            limits = (widths[0] / 2.0, max(widths[-1], _span(inputs.temps[p]) / 2.0))
            for shape in GRADUAL_SHAPES:
                for start in MEMORY_STARTS:
                    def gradual(x: Inputs, w, delay=0.0, p=p, start=start, shape=shape):
                        path = x.path(p, delay)
                        memory = play_memory if shape == "play" else duhem_memory
                        return {f"{shape}{w:.3g}({p},{start})": memory(path, w, memory_start(start, path, w))}
                    fixed = (("probe", p), ("form", "gradual"), ("shape", shape)) + \
                        ((("start", start),) if start != "neutral" else ())
                    out.append(Family("hysteresis", fixed, gradual, "width_c", widths, chosen_probe=mine,
                                      limits=limits, variants=len(GRADUAL_SHAPES) * len(MEMORY_STARTS),
                                      delayed=True, open_above=True))
            for start in MEMORY_STARTS:
                def reversal(x: Inputs, w, delay=0.0, p=p, start=start):
                    path = x.path(p, delay)
                    return {f"relay{w:.3g}C({p},{start})": reversal_relay_state(path, w, memory_start(start, path, w))}
                out.append(Family("hysteresis", (("probe", p), ("form", "reversal"), ("start", start)), reversal,
                                  "width_c", widths, chosen_probe=mine, limits=limits,
                                  variants=len(MEMORY_STARTS), delayed=True, stepwise=True))

    def warm(x: Inputs, tau):
        return {f"exp(-t_on/{tau:.0f})": np.nan_to_num(np.exp(-x.since_on / tau), nan=0.0)}
    warm_taus = tuple(t for t in WARMUP_TAUS_S if t <= duration / 3.0)
    if len(warm_taus) >= 2:
        out.append(Family("warmup", (), warm, "tau_s", warm_taus, limits=(warm_taus[0] / 2.0, duration / 3.0)))

    if inputs.up is not None:
        out.append(Family("g_sensitivity", (), lambda x, _v: {f"g_{ax}": x.up[:, i] for i, ax in enumerate("xyz")}))

    # the scale factor's temperature term is told apart from the bias's own temperature terms only by
    # the input rate changing; a constant input rate (one static position: the Earth rate alone) makes
    # its column a constant times (T - 25), a plain temperature term.  "Changing" is judged against the
    # rate's own size: the same Earth rate recomputed per sample differs from its mean by rounding only
    if inputs.input_rate is not None and _varies(inputs.input_rate):
        p = ctx.primary_probe
        out.append(Family("scale_factor_temperature", (("probe", p),),
                          lambda x, _v: {f"w_in*({p}-25)": x.input_rate * (x.temps[p] - T0_C)}))

    for other in _other_channel_temperatures(ctx, probes):
        def cross(x: Inputs, _v, other=other):
            u = x.temps[other] - T0_C
            return {f"({other}-25)": u, f"({other}-25)^2": u ** 2, f"({other}-25)^3": u ** 3}
        out.append(Family("cross_channel_temperature", (("probe", other),), cross))

    out.append(Family("time_drift", (), lambda x, _v: {"t_hours": (x.time - x.time[0]) / 3600.0}))
    counts: dict[tuple, int] = {}
    for f in out:
        counts[_option_key(f)] = counts.get(_option_key(f), 0) + 1
    return [replace(f, options=counts[_option_key(f)]) for f in out]


def _option_key(f: Family) -> tuple:
    """The families one discrete choice is made among: a kind and form, over probes (and, for a
    hysteresis memory, its start rule and shape)."""
    return (f.kind,) + tuple(kv for kv in f.fixed if kv[0] == "form")


def _widths_for(temp: np.ndarray) -> tuple[float, ...]:
    """Gradual-hysteresis widths that saturate within the run's excursions: up to half the probe's
    temperature span (one full excursion brings the memory to 1 - exp(-2) = 86 % of saturation; a
    wider memory never saturates and is only a slow drift)."""
    return tuple(w for w in GRADUAL_WIDTHS_C if w <= _span(temp) / 2.0)


def _span(temp: np.ndarray) -> float:
    t = temp[np.isfinite(temp)]
    return float(np.ptp(t)) if len(t) else 0.0


def _other_channel_temperatures(ctx: Context, probes: list[str]) -> list[str]:
    """Temperatures that belong to other channels: ``temp_<other channel>`` (e.g. ``temp_y`` while
    fitting ``gyro_x``).  Probes not tied to a channel are covered by ``gradient`` instead."""
    channel_names = set(ctx.channels) | {"x", "y", "z"}
    return [c for c in probes if c in channel_names and c != ctx.channel and c != ctx.primary_probe]


KINDS = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "hysteresis", "warmup",
         "g_sensitivity", "scale_factor_temperature", "cross_channel_temperature", "time_drift")

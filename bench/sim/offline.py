"""Fast, socket-free generation of a whole simulated run as a ``bench.fit.base.Dataset``.

Uses the very same ``GyroPhysics`` as the simulated bench (``record`` = vectorised ``advance_to`` +
``sample``); only the chamber, turntable and power supply are replaced by a program:

* a chamber set-point program of segments (``Profile``):
  ``("hold", T_c, seconds)``  set point jumps to T_c and stays for ``seconds``;
  ``("ramp", T_c, rate_c_per_min)``  set point moves from its current value to T_c at that rate;
  ``("wait", seconds)``  keep the current set point;
  ``("power", "on"|"off")`` and ``("orient", "NUE")`` are instantaneous events.
* the chamber air follows the set point through a first-order lag (``chamber_lag_s``) with a rate
  limit (``chamber_rate_limit_c_per_min``, about +-5 C/min like a Watlow F4 chamber);
* the turntable is static in the given orientation code (body x, y, z directions in E/N/U),
  table rate 0.

Dataset columns (units): ``time_s`` (s, bench time of each sample, the first sample one period
after ``start_time_s``), ``gyro_<ch>`` (deg/h, as output: Earth rate *not* removed; NaN while the
gyro is off or not yet valid), ``temp_<probe>`` (C, rounded to the DS18B20 resolution 0.0625 C by
default), ``freq_<ch>`` (Hz, HRG only), ``orientation`` (str), ``power`` (0/1), ``chamber_pv`` and
``chamber_sp`` (C), ``table_rate_dps`` (deg/s).  ``include_accel`` adds ``accel_<ch>`` (g); the
measured-data CSV v1 does not carry those, so it is off by default.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from bench.errors import PlanError
from bench.fit.base import Dataset
from bench.sim.physics import GyroPhysics, InputBatch, Outputs, PhysicsInputs, orientation_matrix
from bench.sim.scenario import Scenario


@dataclass(frozen=True)
class Segment:
    kind: str                 # hold | ramp | wait | power | orient
    value: Any = None         # T_c, "on"/"off", orientation code
    amount: float = 0.0       # seconds (hold, wait) or C/min (ramp)


@dataclass
class Profile:
    """Chamber set-point program with power and orientation events (see module docstring)."""

    segments: list[Segment]
    start_c: float | None = None       # initial set point/air; default: first hold/ramp target

    @classmethod
    def parse(cls, spec: "Profile | Sequence[Sequence[Any]] | dict", start_c: float | None = None) -> "Profile":
        if isinstance(spec, Profile):
            return spec
        if isinstance(spec, dict):
            unknown = set(spec) - {"segments", "start_c"}
            if unknown:
                raise PlanError(f"profile: unknown key(s) {', '.join(sorted(unknown))}")
            return cls.parse(spec.get("segments", []), spec.get("start_c", start_c))
        segs = []
        for i, raw in enumerate(spec):
            if isinstance(raw, Segment):
                segs.append(raw)
                continue
            if not isinstance(raw, (list, tuple)) or not raw or not isinstance(raw[0], str):
                raise PlanError(f"profile segment {i}: expected (kind, ...), got {raw!r}")
            kind, args = raw[0], list(raw[1:])
            try:
                segs.append(_segment(kind, args))
            except (TypeError, ValueError, PlanError) as exc:
                raise PlanError(f"profile segment {i} {list(raw)!r}: {exc}") from None
        if not any(s.kind in ("hold", "ramp", "wait") for s in segs):
            raise PlanError("profile: needs at least one hold, ramp or wait segment")
        return cls(segs, start_c)

    def initial_setpoint(self) -> float:
        if self.start_c is not None:
            return float(self.start_c)
        for s in self.segments:
            if s.kind in ("hold", "ramp"):
                return float(s.value)
        return 25.0


def _segment(kind: str, args: list) -> Segment:
    def need(n: int) -> None:
        if len(args) != n:
            raise ValueError(f"{kind!r} takes {n} argument(s), got {len(args)}")

    if kind == "hold":
        need(2)
        if float(args[1]) <= 0:
            raise ValueError("hold duration must be > 0 s")
        return Segment("hold", float(args[0]), float(args[1]))
    if kind == "ramp":
        need(2)
        if float(args[1]) <= 0:
            raise ValueError("ramp rate must be > 0 C/min")
        return Segment("ramp", float(args[0]), float(args[1]))
    if kind == "wait":
        need(1)
        if float(args[0]) <= 0:
            raise ValueError("wait duration must be > 0 s")
        return Segment("wait", None, float(args[0]))
    if kind == "power":
        need(1)
        v = args[0]
        if v in (True, "on", 1):
            return Segment("power", True)
        if v in (False, "off", 0):
            return Segment("power", False)
        raise ValueError(f"power must be 'on' or 'off', got {v!r}")
    if kind == "orient":
        need(1)
        orientation_matrix(args[0])
        return Segment("orient", str(args[0]))
    raise ValueError(f"unknown segment kind {kind!r} (hold, ramp, wait, power, orient)")


@dataclass
class _Program:
    """Set point, power and orientation as functions of time (breakpoint lists)."""

    sp_times: list[float] = field(default_factory=list)   # piecewise linear between (t, sp) pairs
    sp_values: list[float] = field(default_factory=list)
    power_events: list[tuple[float, bool]] = field(default_factory=list)
    orient_events: list[tuple[float, str]] = field(default_factory=list)
    end: float = 0.0


def _build_program(profile: Profile, start: float, orientation: str, powered: bool) -> _Program:
    prog = _Program()
    t, sp = start, profile.initial_setpoint()
    prog.sp_times.append(t)
    prog.sp_values.append(sp)
    prog.power_events.append((t, powered))
    prog.orient_events.append((t, orientation))
    for s in profile.segments:
        if s.kind == "hold":
            if s.value != sp:                      # set-point step: a tiny ramp keeps times increasing
                prog.sp_times.append(t + 1e-6)
                prog.sp_values.append(s.value)
            sp = s.value
            t += s.amount
        elif s.kind == "wait":
            t += s.amount
        elif s.kind == "ramp":
            if s.value == sp:
                continue
            t += abs(s.value - sp) / s.amount * 60.0
            sp = s.value
        elif s.kind == "power":
            prog.power_events.append((t, s.value))
            continue
        else:
            prog.orient_events.append((t, s.value))
            continue
        prog.sp_times.append(t)
        prog.sp_values.append(sp)
    prog.end = t
    return prog


def chamber_air(setpoint: np.ndarray, h: float, initial_c: float, lag_s: float, rate_limit_c_per_min: float) -> np.ndarray:
    """Chamber air on a grid of step h: dPV/dt = clip((SP - PV)/lag, +-rate limit), exact per step
    for the unclipped lag (first-order hold is not needed: SP changes slowly against lag_s)."""
    a = math.exp(-h / lag_s)
    max_step = rate_limit_c_per_min / 60.0 * h
    sp = setpoint.tolist()
    out = [0.0] * len(sp)
    pv = float(initial_c)
    for k, target in enumerate(sp):
        step = (target - pv) * (1.0 - a)
        if step > max_step:
            step = max_step
        elif step < -max_step:
            step = -max_step
        pv += step
        out[k] = pv
    return np.array(out)


class ProgramInputs(PhysicsInputs):
    """Physics inputs from precomputed arrays on a uniform grid (vectorised ``batch``)."""

    def __init__(self, start: float, h: float, air: np.ndarray, powered: np.ndarray, on_time: np.ndarray,
                 orient_idx: np.ndarray, matrices: np.ndarray) -> None:
        self._start, self._h = start, h
        self._air, self._powered, self._on_time = air, powered, on_time
        self._orient_idx, self._matrices = orient_idx, matrices
        super().__init__(self._air_at, self._matrix_at, lambda t: (0.0, 0.0, 0.0), self._powered_at, self._on_at)

    def _index(self, times: np.ndarray) -> np.ndarray:
        k = np.rint((np.asarray(times, dtype=float) - self._start) / self._h).astype(np.int64)
        return np.clip(k, 0, self._air.size - 1)

    def _air_at(self, t: float) -> float:
        return float(self._air[self._index(np.array([t]))[0]])

    def _matrix_at(self, t: float) -> np.ndarray:
        return self._matrices[self._orient_idx[self._index(np.array([t]))[0]]]

    def _powered_at(self, t: float) -> bool:
        return bool(self._powered[self._index(np.array([t]))[0]])

    def _on_at(self, t: float) -> float | None:
        v = self._on_time[self._index(np.array([t]))[0]]
        return None if np.isnan(v) else float(v)

    def batch(self, times: np.ndarray) -> InputBatch:
        k = self._index(times)
        return InputBatch(self._air[k], self._matrices[self._orient_idx[k]], np.zeros((k.size, 3)),
                          self._powered[k], self._on_time[k])


@dataclass
class Simulation:
    dataset: Dataset
    outputs: Outputs            # true bias, node temperatures, ... at the dataset's samples
    physics: GyroPhysics


def simulate_full(scenario: Scenario | str, profile: Profile | Sequence | dict, sample_period_s: float = 1.0,
                  orientation: str = "NUE", seed: int | None = None, *, start_time_s: float = 0.0,
                  powered_at_start: bool = True, probe_resolution_c: float | None = 0.0625,
                  chamber_lag_s: float = 60.0, chamber_rate_limit_c_per_min: float = 5.0,
                  include_accel: bool = False) -> Simulation:
    """Like ``simulate`` but also returns the true outputs (bias, node temperatures) and the model."""
    if isinstance(scenario, str):
        scenario = Scenario.builtin(scenario)
    if seed is not None:
        scenario = scenario.with_changes(seed=int(seed))
    if not sample_period_s > 0:
        raise PlanError(f"sample_period_s must be > 0, got {sample_period_s}")
    prof = Profile.parse(profile)
    orientation_matrix(orientation)
    prog = _build_program(prof, start_time_s, orientation, powered_at_start)

    # physics grid: the scenario sub-step, shortened so that a whole number fits in a sample period
    every = max(1, math.ceil(sample_period_s / scenario.thermal.substep_s - 1e-9))
    h = sample_period_s / every
    n_samples = int(math.floor((prog.end - start_time_s) / sample_period_s + 1e-9))
    if n_samples < 1:
        raise PlanError(f"profile lasts {prog.end - start_time_s:.3g} s, shorter than one sample period")
    n_grid = n_samples * every
    grid = start_time_s + h * np.arange(n_grid + 1)
    sp = np.interp(grid, prog.sp_times, prog.sp_values)
    air = chamber_air(sp, h, prof.initial_setpoint(), chamber_lag_s, chamber_rate_limit_c_per_min)

    powered = np.zeros(grid.size, dtype=bool)
    on_time = np.full(grid.size, np.nan)
    state, since = False, math.nan
    for t_ev, on in prog.power_events:
        k0 = int(np.searchsorted(grid, t_ev - 1e-9))
        if on and not state:
            since = t_ev
        state = on
        powered[k0:] = on
        on_time[k0:] = since if on else np.nan
    codes = []
    orient_idx = np.zeros(grid.size, dtype=np.int64)
    for t_ev, code in prog.orient_events:
        if code not in codes:
            codes.append(code)
        orient_idx[int(np.searchsorted(grid, t_ev - 1e-9)):] = codes.index(code)
    matrices = np.array([orientation_matrix(c) for c in codes])

    inputs = ProgramInputs(start_time_s, h, air, powered, on_time, orient_idx, matrices)
    physics = GyroPhysics(scenario, start_time_s, inputs, output_period_s=sample_period_s, substep_s=h)
    out = physics.record(n_grid, period_s=sample_period_s, every=every)

    k = np.arange(1, n_samples + 1) * every
    cols: dict[str, np.ndarray] = {"time_s": out.times.copy()}
    bad = ~out.valid
    for i, ch in enumerate(scenario.channels):
        g = out.rate_dph[:, i].copy()
        g[bad] = np.nan
        cols[f"gyro_{ch}"] = g
    for p, v in out.probes_c.items():
        cols[f"temp_{p}"] = np.round(v / probe_resolution_c) * probe_resolution_c if probe_resolution_c else v.copy()
    if out.freq_hz is not None:
        for i, ch in enumerate(scenario.channels):
            f = out.freq_hz[:, i].copy()
            f[bad] = np.nan
            cols[f"freq_{ch}"] = f
    cols["orientation"] = np.array(codes, dtype=object)[orient_idx[k]]
    cols["power"] = powered[k].astype(float)
    cols["chamber_pv"] = air[k]
    cols["chamber_sp"] = sp[k]
    cols["table_rate_dps"] = np.zeros(n_samples)
    if include_accel:
        for i, ch in enumerate(scenario.channels):
            cols[f"accel_{ch}"] = out.accel_g[:, i].copy()
    meta = {
        "gyro_id": f"sim-{scenario.name}",
        "gyro_type": scenario.gyro_type,
        "latitude_deg": repr(float(scenario.latitude_deg)),
        "sample_period_s": repr(float(sample_period_s)),
        "channel_probes": scenario.channel_probe_map(),
        "scenario": scenario.name,
        "seed": str(scenario.seed),
        "notes": f"simulated by bench.sim.offline (scenario {scenario.name}, seed {scenario.seed})",
    }
    return Simulation(Dataset(cols, meta), out, physics)


def simulate(scenario: Scenario | str, profile: Profile | Sequence | dict, sample_period_s: float = 1.0,
             orientation: str = "NUE", seed: int | None = None, **options: Any) -> Dataset:
    """A whole run as a Dataset (see module docstring for columns and units).

    ``scenario``: a Scenario or the name of a built-in one; ``profile``: Profile or list of segment
    tuples; ``seed`` overrides the scenario's seed.  Options: start_time_s, powered_at_start,
    probe_resolution_c (None = exact), chamber_lag_s, chamber_rate_limit_c_per_min, include_accel.
    """
    return simulate_full(scenario, profile, sample_period_s, orientation, seed, **options).dataset


def eight_position_profile(temperature_c: float, soak_s: float, dwell_s: float,
                           codes: Iterable[str] = ("ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")) -> list:
    """Seed 000 section 3.2 eight-position test at one temperature: soak, then dwell in each code."""
    prof: list = [("hold", temperature_c, soak_s)]
    for c in codes:
        prof += [("orient", c), ("wait", dwell_s)]
    return prof

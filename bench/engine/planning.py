"""Plan validation, duration estimates and planned set-point profiles (no hardware involved).

``validate_plan`` refuses a plan with a ``PlanError`` naming the step and the value before anything
moves.  ``plan_summary`` adds per-step duration estimates (bench seconds), the total and a few
facts for display.  ``setpoint_profile`` / ``part_correlation`` give the planned chamber set-point
profile of (a part of) a plan and the Pearson correlation between two parts (S001: a validation
run must correlate weakly with the modelling run, r < 0.4).

Estimates: a ``SetChamber`` takes no time of its own (the following soak/wait absorbs the
chamber's travel); a ramp takes |target - previous set point| / rate; a ``WaitStable`` takes its
``expected_s``; a table move takes the largest axis travel / rate limit + accel time + settle.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.config import BenchConfig
from bench.engine.config import EngineConfig
from bench.engine.orientation import orientation_problem, solve_angles, solver_available
from bench.engine.steps import (Fit, GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak,
                                TableRate, WaitStable, WeakCorrelation, step_labels)
from bench.errors import BenchError, PlanError


def setpoint_limits(config: BenchConfig) -> tuple[float, float]:
    """Allowed chamber set points: inside both the chamber's and the gyro's limits."""
    return (max(config.chamber.setpoint_min_c, config.gyro_limits.min_c),
            min(config.chamber.setpoint_max_c, config.gyro_limits.max_c))


def _where(index: int, step: Any) -> str:
    return f"step {index} ({step.kind}: {step.describe()})"


def _check_temperature(index: int, step: Any, what: str, value: float, config: BenchConfig) -> None:
    lo, hi = setpoint_limits(config)
    if not np.isfinite(value) or value < lo or value > hi:
        raise PlanError(
            f"{_where(index, step)}: {what} {value:g} C is outside the allowed range {lo:g}..{hi:g} C "
            f"(chamber set point {config.chamber.setpoint_min_c:g}..{config.chamber.setpoint_max_c:g} C, "
            f"gyro {config.gyro_limits.min_c:g}..{config.gyro_limits.max_c:g} C)")


def _check_positive(index: int, step: Any, what: str, value: float, allow_zero: bool = False) -> None:
    ok = np.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        raise PlanError(f"{_where(index, step)}: {what} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")


def _validate_step(index: int, step: Any, config: BenchConfig) -> None:
    if isinstance(step, SetChamber):
        _check_temperature(index, step, "set point", step.setpoint_c, config)
    elif isinstance(step, Ramp):
        _check_temperature(index, step, "ramp target", step.target_c, config)
        _check_positive(index, step, "ramp rate (C/min)", step.rate_c_per_min)
        if step.rate_c_per_min > config.chamber.max_ramp_c_per_min:
            raise PlanError(f"{_where(index, step)}: ramp rate {step.rate_c_per_min:g} C/min exceeds the chamber "
                            f"maximum {config.chamber.max_ramp_c_per_min:g} C/min (chamber.max_ramp_c_per_min)")
        if step.until_probes_c is not None:
            _check_temperature(index, step, "probe target", step.until_probes_c, config)
            _check_positive(index, step, "probe tolerance", step.probe_tol_c)
            _check_positive(index, step, "until_timeout_s", step.until_timeout_s)
    elif isinstance(step, Soak):
        _check_positive(index, step, "soak duration_s", step.duration_s, allow_zero=True)
    elif isinstance(step, Record):
        _check_positive(index, step, "record duration_s", step.duration_s)
        if not step.labels:
            raise PlanError(f"{_where(index, step)}: a record needs labels (temperature point, position...)")
    elif isinstance(step, WaitStable):
        _check_positive(index, step, "tol_c", step.tol_c)
        _check_positive(index, step, "stable_s", step.stable_s)
        _check_positive(index, step, "rate_window_s", step.rate_window_s)
        if step.probe_rate_c_per_min is not None:
            _check_positive(index, step, "probe_rate_c_per_min", step.probe_rate_c_per_min)
        if step.probe_tol_c is not None:
            _check_positive(index, step, "probe_tol_c", step.probe_tol_c)
        if not (step.timeout_s >= step.stable_s):
            raise PlanError(f"{_where(index, step)}: timeout_s {step.timeout_s:g} is shorter than "
                            f"stable_s {step.stable_s:g}")
    elif isinstance(step, Orient):
        problem = orientation_problem(step.code)
        if problem:
            raise PlanError(f"{_where(index, step)}: {problem}")
        _check_positive(index, step, "timeout_s", step.timeout_s)
        if solver_available():
            try:
                solve_angles(step.code, config.turntable.geometry)
            except BenchError as exc:
                raise PlanError(f"{_where(index, step)}: the turntable cannot reach {step.code}: {exc}") from None
    elif isinstance(step, TableRate):
        limit = config.turntable.rate_limit_dps
        if not np.isfinite(step.rate_dps) or abs(step.rate_dps) > limit:
            raise PlanError(f"{_where(index, step)}: rate {step.rate_dps:g} deg/s exceeds the turntable rate "
                            f"limit {limit:g} deg/s (turntable.rate_limit_dps)")
    elif isinstance(step, Fit):
        if not step.models:
            raise PlanError(f"{_where(index, step)}: no model named")
    elif isinstance(step, GyroPower):
        pass


def validate_plan(plan: Plan, config: BenchConfig) -> None:
    """Raise ``PlanError`` for the first problem found; return None for a good plan."""
    if not plan.steps:
        raise PlanError(f"plan {plan.name!r} has no steps")
    for index, step in enumerate(plan.steps):
        _validate_step(index, step, config)
    parts = {s.part for s in plan.steps if s.part}
    for constraint in plan.constraints:
        for part in (constraint.part_a, constraint.part_b):
            if part not in parts:
                raise PlanError(f"plan {plan.name!r}: constraint {constraint.kind} names part {part!r} "
                                f"but no step has that part (parts: {sorted(parts)})")
        r = part_correlation(plan, constraint)
        if not abs(r) < constraint.max_abs_r:
            raise PlanError(
                f"plan {plan.name!r}: planned chamber set-point profiles of parts {constraint.part_a!r} and "
                f"{constraint.part_b!r} correlate with r = {r:.3f}; a weakly correlated validation needs "
                f"|r| < {constraint.max_abs_r:g}")


# ---- estimates -----------------------------------------------------------------------------------

@dataclass
class _SimState:
    setpoint_c: float
    angles: tuple[float, float] | None = None


def _angle_travel(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def estimate_step_s(step: Any, state: _SimState, config: BenchConfig,
                    engine_config: EngineConfig | None = None) -> float:
    """Planned bench duration of ``step`` from ``state``; updates ``state`` to after the step."""
    ec = engine_config or EngineConfig()
    if isinstance(step, SetChamber):
        state.setpoint_c = step.setpoint_c
        return 0.0
    if isinstance(step, Ramp):
        seconds = abs(step.target_c - state.setpoint_c) / step.rate_c_per_min * 60.0
        state.setpoint_c = step.target_c
        if step.until_probes_c is not None:
            seconds += min(step.until_timeout_s, 1800.0)
        return seconds
    if isinstance(step, (Soak, Record)):
        return float(step.duration_s)
    if isinstance(step, WaitStable):
        return float(min(step.expected_s, step.timeout_s))
    if isinstance(step, Orient):
        tt = config.turntable
        travel = 180.0
        if solver_available():
            try:
                target = solve_angles(step.code, tt.geometry)
            except BenchError:
                target = None
            if target is not None:
                travel = (max(_angle_travel(a, b) for a, b in zip(target, state.angles))
                          if state.angles else 180.0)
                state.angles = (float(target[0]), float(target[1]))
        return travel / tt.rate_limit_dps + tt.rate_limit_dps / tt.acceleration_dps2 + ec.table_settle_s
    return 0.0


def step_estimates(plan: Plan, config: BenchConfig, engine_config: EngineConfig | None = None) -> list[float]:
    state = _SimState(plan.start_c)
    return [estimate_step_s(step, state, config, engine_config) for step in plan.steps]


def plan_summary(plan: Plan, config: BenchConfig, engine_config: EngineConfig | None = None) -> dict[str, Any]:
    """Validate ``plan`` and describe it: steps with estimates and start offsets, totals."""
    validate_plan(plan, config)
    estimates = step_estimates(plan, config, engine_config)
    steps, offset = [], 0.0
    record_s = 0.0
    for index, (step, est) in enumerate(zip(plan.steps, estimates)):
        labels = step_labels(step)
        steps.append({"index": index, "kind": step.kind, "describe": step.describe(), "part": step.part,
                      "est_s": est, "start_offset_s": offset, "labels": labels})
        offset += est
        if labels is not None:
            record_s += est
    setpoints = [s.setpoint_c for s in plan.steps if isinstance(s, SetChamber)]
    setpoints += [s.target_c for s in plan.steps if isinstance(s, Ramp)]
    return {
        "name": plan.name,
        "steps": steps,
        "n_steps": len(steps),
        "total_bench_s": offset,
        "total_bench_h": offset / 3600.0,
        "recorded_bench_s": record_s,
        "setpoint_range_c": [min(setpoints), max(setpoints)] if setpoints else None,
        "orientations": sorted({s.code for s in plan.steps if isinstance(s, Orient)}),
        "constraints": [{**c.model_dump(), "r": part_correlation(plan, c)} for c in plan.constraints],
    }


# ---- planned set-point profiles ------------------------------------------------------------------

def setpoint_profile(plan: Plan, part: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints (t_s, setpoint_c) of the planned chamber set point, piecewise linear.

    With ``part``: only the span from the first to the last step of that part, time measured from
    the start of that span.  A ``SetChamber`` is a jump (two breakpoints at the same time).
    """
    state = _SimState(plan.start_c)
    config = BenchConfig()
    t = 0.0
    times: list[float] = []
    values: list[float] = []
    indexes = [i for i, s in enumerate(plan.steps) if part is None or s.part == part]
    if not indexes:
        raise PlanError(f"plan {plan.name!r} has no steps of part {part!r}")
    first, last = indexes[0], indexes[-1]
    for index, step in enumerate(plan.steps):
        before = state.setpoint_c
        duration = estimate_step_s(step, state, config)
        if first <= index <= last:
            times.append(t)
            values.append(before)
            if isinstance(step, SetChamber):
                times.append(t)
                values.append(state.setpoint_c)
            elif isinstance(step, Ramp):
                times.append(t + abs(step.target_c - before) / step.rate_c_per_min * 60.0)
                values.append(step.target_c)
            times.append(t + duration)
            values.append(state.setpoint_c)
        t += duration
    times_a = np.asarray(times, dtype=float)
    return times_a - times_a[0], np.asarray(values, dtype=float)


def sample_profile(times: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Evaluate a breakpoint profile (jumps allowed: the later value wins at a jump time)."""
    # np.interp needs increasing x: move the earlier of repeated breakpoints back a tiny amount.
    x = times.astype(float).copy()
    for i in range(len(x) - 1, 0, -1):
        if x[i - 1] >= x[i]:
            x[i - 1] = x[i] - 1e-6
    return np.interp(at, x, values)


def part_correlation(plan: Plan, constraint: WeakCorrelation) -> float:
    """Pearson r between the planned set-point profiles of two parts.

    Alignment: both profiles are taken on elapsed time from the start of their part and resampled
    every ``resample_s`` over the shorter of the two durations.
    """
    ta, va = setpoint_profile(plan, constraint.part_a)
    tb, vb = setpoint_profile(plan, constraint.part_b)
    span = min(ta[-1], tb[-1])
    if span <= constraint.resample_s:
        raise PlanError(f"plan {plan.name!r}: parts {constraint.part_a!r}/{constraint.part_b!r} are too short "
                        f"({span:g} s) to compare set-point profiles")
    at = np.arange(0.0, span, constraint.resample_s)
    a = sample_profile(ta, va, at)
    b = sample_profile(tb, vb, at)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        which = constraint.part_a if np.ptp(a) == 0 else constraint.part_b
        raise PlanError(f"plan {plan.name!r}: the set-point profile of part {which!r} is constant over the "
                        f"compared span; correlation is undefined")
    return float(np.corrcoef(a, b)[0, 1])

"""Pieces shared by the procedures: how to settle at a temperature point (fixed soak or
wait-until-stable), and parameter types."""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict

from bench.engine import SetChamber, Soak, WaitStable
from bench.fit.formula import MAX_FORMULA_CHARS
from bench.engine.steps import Labels, Step


# ---- parameter types: strict (no true/false for a number), finite, bounded by physics and the bench
MAX_PLAN_DAYS = 30.0             # a whole plan, bench time
MAX_HOURS = MAX_PLAN_DAYS * 24.0
MAX_MINUTES = MAX_HOURS * 60.0
MIN_RAMP_C_PER_MIN = 0.01        # slower is not a ramp any chamber controller holds (upper limit: bench config)
TEMPERATURE_LIMITS_C = (-100.0, 200.0)
MAX_POINTS = 200                 # temperature points / positions / legs of one plan


# Strict: true/false is not a number (nor 1.0 a count) and text is not a number; ints are fine for floats
Real = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Count = Annotated[int, Strict()]
Hours = Annotated[Real, Field(gt=0, le=MAX_HOURS, description=f"hours, at most {MAX_HOURS:g}")]
Minutes = Annotated[Real, Field(gt=0, le=MAX_MINUTES, description=f"minutes, at most {MAX_MINUTES:g}")]
MinutesOrZero = Annotated[Real, Field(ge=0, le=MAX_MINUTES, description=f"minutes, at most {MAX_MINUTES:g}")]
Celsius = Annotated[Real, Field(ge=TEMPERATURE_LIMITS_C[0], le=TEMPERATURE_LIMITS_C[1],
                                description="degrees C (the bench's own limits are checked on the plan)")]
Tolerance = Annotated[Real, Field(gt=0, le=50.0, description="degrees C")]
RampRate = Annotated[Real, Field(ge=MIN_RAMP_C_PER_MIN, le=100.0,
                                 description=f"C/min, at least {MIN_RAMP_C_PER_MIN} (at most the chamber's "
                                             f"max_ramp_c_per_min, checked on the plan)")]
Flag = Annotated[bool, Strict()]


def _check_model(name: str) -> str:
    from bench.fit.catalog import check_model_name   # a registered model or a formula within the limits

    return check_model_name(name)


ModelName = Annotated[str, Field(min_length=1, max_length=MAX_FORMULA_CHARS), AfterValidator(_check_model)]
ModelList = Annotated[list[ModelName], Field(min_length=1, max_length=10)]
CelsiusPoints = Annotated[list[Celsius], Field(min_length=1, max_length=MAX_POINTS)]


class StableParams(BaseModel):
    """Wait-until-stable criterion: chamber within +-tol_c of the set point and every gyro probe
    changing less than probe_rate_c_per_min (slope over rate_window_min) for stable_min minutes;
    optionally every probe within +-probe_tol_c of the set point.  Gives up after timeout_h."""

    model_config = ConfigDict(extra="forbid")
    tol_c: Tolerance = 1.0
    probe_rate_c_per_min: Annotated[Real, Field(gt=0, le=100.0)] = 0.05
    probe_tol_c: Tolerance | None = None
    rate_window_min: Minutes = 5.0
    stable_min: Minutes = 10.0
    timeout_h: Hours = 8.0
    expected_h: Hours = 3.0


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def hold_at(setpoint_c: float, settle: Literal["soak", "stable"], soak_h: float, stable: StableParams,
            record: Labels | None = None, part: str | None = None) -> list[Step]:
    """Set the chamber and hold: a fixed soak of ``soak_h`` or wait until stable."""
    steps: list[Step] = [SetChamber(setpoint_c=setpoint_c, part=part)]
    if settle == "soak":
        steps.append(Soak(duration_s=soak_h * 3600.0, record=record, part=part))
    else:
        steps.append(WaitStable(tol_c=stable.tol_c, probe_rate_c_per_min=stable.probe_rate_c_per_min,
                                probe_tol_c=stable.probe_tol_c, rate_window_s=stable.rate_window_min * 60.0,
                                stable_s=stable.stable_min * 60.0, timeout_s=stable.timeout_h * 3600.0,
                                expected_s=min(stable.expected_h, stable.timeout_h) * 3600.0,
                                record=record, part=part))
    return steps


def frange(start: float, stop: float, step: float) -> list[float]:
    """start, start+step, ... up to and including stop (for the default point lists)."""
    n = int(round((stop - start) / step))
    return [round(start + i * step, 6) for i in range(n + 1)]

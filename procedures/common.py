"""Pieces shared by the procedures: how to settle at a temperature point (fixed soak or
wait-until-stable), and parameter types."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from bench.engine import SetChamber, Soak, WaitStable
from bench.engine.steps import Labels, Step


class StableParams(BaseModel):
    """Wait-until-stable criterion: chamber within +-tol_c of the set point and every gyro probe
    changing less than probe_rate_c_per_min (slope over rate_window_min) for stable_min minutes;
    optionally every probe within +-probe_tol_c of the set point.  Gives up after timeout_h."""

    model_config = ConfigDict(extra="forbid")
    tol_c: float = Field(1.0, gt=0)
    probe_rate_c_per_min: float = Field(0.05, gt=0)
    probe_tol_c: float | None = Field(None, gt=0)
    rate_window_min: float = Field(5.0, gt=0)
    stable_min: float = Field(10.0, gt=0)
    timeout_h: float = Field(8.0, gt=0)
    expected_h: float = Field(3.0, gt=0)


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

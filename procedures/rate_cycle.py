"""S001 (four-probe, 37-term patent): temperature cycles between -20 and +50 C at several rates,
then a weakly correlated validation run.

Modelling part ("model"): the chamber makes a temperature cycle over -20..+50 C (here a stepped
cycle up and back down, ``cycle_step_c`` apart, ``cycle_hold_min`` per step: it gives the
temperature terms), then cycles at +-2, +-1, +-0.5, +-0.2 and +-0.1 C/min (the rate and
temperature x rate terms), each ramp followed by a ``dwell_min`` hold at the extreme.  Four gyro
probes (T1..T4) are read throughout (configure four DS18B20 positions).

Validation part ("validation"): legs (target, rate, hold) whose holds give the bias repeatability
and stability of the compensated output.  The patent requires the validation chamber temperature to
correlate weakly with the modelling one (r < 0.4).  Enforced before the run: the plan carries a
``WeakCorrelation`` constraint checked by ``build`` and again by the engine's validation; it compares
the two *planned chamber set-point profiles*, each on elapsed time from the start of its part,
resampled every 60 s over the shorter duration; |r| must be < ``max_abs_r`` (a strongly
anti-correlated profile is not weakly correlated either).
"""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from bench.engine import Fit, GyroPower, Plan, Ramp, SetChamber, Soak, WeakCorrelation, part_correlation
from bench.errors import PlanError
from procedures.common import (MAX_POINTS, Celsius, Flag, Hours, Minutes, MinutesOrZero, ModelList, RampRate, Real,
                               _Params, frange)

NAME = "rate_cycle"
DESCRIPTION = ("S001 modelling run: -20..+50 C temperature cycle then cycles at +-2, 1, 0.5, 0.2, 0.1 C/min "
               "with four probes; validation run whose set-point profile correlates weakly (|r| < 0.4); "
               "37-term model fit")


class Leg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    target_c: Celsius
    rate_c_per_min: RampRate
    hold_min: MinutesOrZero


def _default_validation() -> list[Leg]:
    return [Leg(target_c=t, rate_c_per_min=r, hold_min=h) for t, r, h in (
        (30.0, 1.5, 90.0), (0.0, 0.7, 90.0), (45.0, 1.5, 90.0), (-10.0, 1.0, 90.0),
        (20.0, 0.3, 90.0), (-15.0, 1.5, 90.0), (35.0, 0.8, 90.0), (5.0, 1.5, 90.0))]


class Params(_Params):
    low_c: Celsius = -20.0
    high_c: Celsius = 50.0
    initial_soak_h: Hours = 2.0
    cycle_step_c: Real = Field(10.0, ge=0.1, le=300.0)
    cycle_hold_min: Minutes = 60.0
    rates_c_per_min: list[RampRate] = Field(default_factory=lambda: [2.0, 1.0, 0.5, 0.2, 0.1], min_length=1,
                                            max_length=MAX_POINTS)
    dwell_min: MinutesOrZero = 30.0
    include_validation: Flag = True
    validation: list[Leg] = Field(default_factory=_default_validation, max_length=MAX_POINTS)
    max_abs_r: Real = Field(0.4, gt=0, le=1)
    fit_models: ModelList = Field(default_factory=lambda: ["patent37"])


def _modelling(p: Params) -> list:
    rec = {"set": "model"}
    steps: list = [SetChamber(setpoint_c=p.low_c, part="model"),
                   Soak(duration_s=p.initial_soak_h * 3600.0, part="model")]
    up = frange(p.low_c, p.high_c, p.cycle_step_c)
    if up[-1] != p.high_c:
        up.append(p.high_c)
    for point in up[1:] + up[-2::-1]:
        steps += [SetChamber(setpoint_c=point, part="model"),
                  Soak(duration_s=p.cycle_hold_min * 60.0, part="model",
                       record={**rec, "phase": "temperature_cycle", "temperature_c": point})]
    for rate in p.rates_c_per_min:
        for target, direction in ((p.high_c, "up"), (p.low_c, "down")):
            labels = {**rec, "phase": "rate_cycle", "rate_c_per_min": rate, "direction": direction}
            steps.append(Ramp(target_c=target, rate_c_per_min=rate, part="model", record=labels))
            if p.dwell_min > 0:
                steps.append(Soak(duration_s=p.dwell_min * 60.0, part="model",
                                  record={**labels, "phase": "dwell", "temperature_c": target}))
    return steps


def _validation(p: Params) -> list:
    steps: list = []
    for k, leg in enumerate(p.validation):
        labels = {"set": "validation", "leg": k}
        steps.append(Ramp(target_c=leg.target_c, rate_c_per_min=leg.rate_c_per_min, part="validation",
                          record={**labels, "phase": "ramp"}))
        if leg.hold_min > 0:
            steps.append(Soak(duration_s=leg.hold_min * 60.0, part="validation",
                              record={**labels, "phase": "hold", "temperature_c": leg.target_c}))
    return steps


def build(params: Params | None = None) -> Plan:
    p = params or Params()
    steps: list = [GyroPower(on=True)] + _modelling(p)
    constraints = []
    if p.include_validation:
        if not p.validation:
            raise PlanError(f"{NAME}: include_validation is set but the validation profile has no legs")
        steps += _validation(p)
        constraints.append(WeakCorrelation(part_a="model", part_b="validation", max_abs_r=p.max_abs_r))
    steps += [GyroPower(on=False),
              Fit(models=p.fit_models, options={"procedure": NAME, "train": {"set": "model"},
                                                "validate": {"set": "validation"} if p.include_validation else None})]
    plan = Plan(name=NAME, steps=steps, params=p.model_dump(mode="json"), constraints=constraints)
    for constraint in constraints:   # refuse here already, so the API rejects the parameters
        r = part_correlation(plan, constraint)
        if not abs(r) < constraint.max_abs_r:
            raise PlanError(f"{NAME}: the validation set-point profile correlates with the modelling one "
                            f"(r = {r:.3f}); the patent needs a weakly correlated validation, |r| < "
                            f"{constraint.max_abs_r:g}. Change the validation legs.")
    return plan


def correlation(params: Params | None = None) -> float:
    """r between the planned modelling and validation set-point profiles (for display)."""
    p = params or Params()
    plan = Plan(name=NAME, steps=[GyroPower(on=True)] + _modelling(p) + _validation(p))
    return part_correlation(plan, WeakCorrelation(part_a="model", part_b="validation"))

"""S002 HRG: frequency-temperature points, then cool / soak / ramp for the compensation model.

Frequency-temperature part: "chamber -40..50 C, one point every 10 C; at each point soak 5 h and
take the resonance frequency and the temperature-circuit value of the 5th hour (100 s smoothing)."
The DS18B20 probes on the gyro case are the temperature reference.  Here each point is a soak of
``soak_h - record_min`` followed by a labelled record of ``record_min`` (the 5th hour).

Dynamic part: "from room temperature cool in set-point mode; once the chamber reaches -40 C soak
5 h; then warm at 1 C/min until all three gyros read 50 C."  The cool-down is a set-point jump
followed by a wait until the chamber is within ``cool_tol_c`` of -40 C; the ramp continues after the
chamber reaches 50 C until every gyro probe reads 50 C (within ``probe_tol_c``).

Fits: the reverse frequency -> temperature fit and the HRG temperature compensation.
"""
from __future__ import annotations

from pydantic import Field

from bench.engine import Fit, GyroPower, Plan, Ramp, Record, SetChamber, Soak, WaitStable
from procedures.common import (Celsius, CelsiusPoints, Flag, Hours, Minutes, ModelList, RampRate, Tolerance, _Params,
                               frange)

NAME = "hrg_calibration"
DESCRIPTION = ("S002 HRG: frequency-temperature points -40..50 C every 10 C with 5 h soak (DS18B20 "
               "reference), then cool to -40 C, soak 5 h, ramp +1 C/min until every gyro probe reads 50 C")


class Params(_Params):
    points_c: CelsiusPoints = Field(default_factory=lambda: frange(-40.0, 50.0, 10.0))
    soak_h: Hours = 5.0
    record_min: Minutes = 60.0
    include_dynamic: Flag = True
    cold_c: Celsius = -40.0
    cool_tol_c: Tolerance = 1.0
    cool_expected_h: Hours = 2.0
    cool_timeout_h: Hours = 6.0
    cold_soak_h: Hours = 5.0
    rate_c_per_min: RampRate = 1.0
    end_c: Celsius = 50.0
    probe_tol_c: Tolerance = 0.25
    until_timeout_h: Hours = 3.0
    fit_models: ModelList = Field(default_factory=lambda: ["hrg_reverse", "hrg"])


def build(params: Params | None = None) -> Plan:
    p = params or Params()
    record_s = p.record_min * 60.0
    soak_s = max(0.0, p.soak_h * 3600.0 - record_s)
    steps: list = [GyroPower(on=True)]
    for point in p.points_c:
        steps += [SetChamber(setpoint_c=point), Soak(duration_s=soak_s),
                  Record(duration_s=record_s, labels={"set": "frequency_temperature", "temperature_c": point})]
    if p.include_dynamic:
        rec = {"set": "dynamic"}
        steps += [
            SetChamber(setpoint_c=p.cold_c),
            WaitStable(tol_c=p.cool_tol_c, probe_rate_c_per_min=None, stable_s=60.0,
                       timeout_s=p.cool_timeout_h * 3600.0, expected_s=p.cool_expected_h * 3600.0,
                       record={**rec, "phase": "cool"}),
            Soak(duration_s=p.cold_soak_h * 3600.0, record={**rec, "phase": "cold_soak"}),
            Ramp(target_c=p.end_c, rate_c_per_min=p.rate_c_per_min, until_probes_c=p.end_c,
                 probe_tol_c=p.probe_tol_c, until_timeout_s=p.until_timeout_h * 3600.0,
                 record={**rec, "phase": "ramp"}),
        ]
    steps += [GyroPower(on=False),
              Fit(models=p.fit_models, options={"procedure": NAME, "reference": "probes",
                                                "points": {"set": "frequency_temperature"},
                                                "dynamic": {"set": "dynamic"} if p.include_dynamic else None})]
    return Plan(name=NAME, steps=steps, params=p.model_dump(mode="json"))

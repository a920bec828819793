"""S000 3.3 dynamic test: soak at +40 C, power on, ramp -1 C/min to -30 C, hold 20 min.

"The system stands in the chamber in position 北天东 (NUE); the chamber starts at +40 C and soaks
for several hours; 10 min after the system is powered the chamber goes from +40 C to -30 C at
-1 C/min, then holds 20 min; the gyro outputs and temperature sensors are recorded throughout."

Recorded phases: ``warmup`` (the 10 min after power-on), ``ramp`` and ``cold_hold``; the dynamic
model (temperature, gradient and rate terms) is fitted at the end (unless ``fit=false``: a held-out run
that only records, so the gyro's coefficients stay those of its modelling run).  ``soak_h`` default 4 h stands
for the paper's "several hours".

Orientation: S000 mounts the system 北天东 (NUE: x North, y Up, z East) for this test.  NUE keeps the
gyro's y axis vertical, which the default two-axis geometry (outer axis vertical, inner axis along
North at rest, gyro mounted ENU, so body y always lies on the horizontal inner axis) cannot reach.
The default is therefore ``orientation=None``: the table is not moved and the gyro stays as mounted;
the stored segments record the orientation code the table angles actually realise
(``bench.devices.orientation.code_at`` with the bench's geometry, in ``bench.engine.sqlstore``).
To reproduce S000's NUE, describe the test's mounting in the bench config:
``turntable.geometry.mounting = "NUE"`` (gyro x North, y Up, z East with the table at 0, 0) makes the
default run record NUE with the table at rest at zero; or use a geometry that reaches NUE (e.g. gyro x
on the inner axis: ``inner_axis = [1, 0, 0]``) and pass ``--param orientation=NUE``.  Plan validation
refuses a code the geometry cannot reach and names the reason.
"""
from __future__ import annotations

from pydantic import Field

from bench.engine import Fit, GyroPower, Orient, Plan, Ramp, SetChamber, Soak
from procedures.common import Celsius, Flag, Hours, Minutes, ModelList, RampRate, _Params

NAME = "thermal_ramp"
DESCRIPTION = ("S000 3.3 dynamic test, gyro as mounted (S000 mounts it NUE): soak +40 C, power on, 10 min, "
               "ramp -1 C/min to -30 C, hold 20 min, recording throughout; dynamic model fit")


class Params(_Params):
    orientation: str | None = Field(None, max_length=3)   # None: leave the table (gyro as mounted); S000: "NUE"
    start_c: Celsius = 40.0
    soak_h: Hours = 4.0
    warmup_min: Minutes = 10.0
    rate_c_per_min: RampRate = 1.0
    end_c: Celsius = -30.0
    final_hold_min: Minutes = 20.0
    fit_models: ModelList = Field(default_factory=lambda: ["dynamic"])
    # False: record only, no Fit step (a held-out run for close-the-loop: the gyro's accepted coefficients
    # stay those fitted on the modelling run)
    fit: Flag = True


def build(params: Params | None = None) -> Plan:
    p = params or Params()
    rec = {"set": "dynamic", **({"position": p.orientation} if p.orientation else {})}
    steps = [Orient(code=p.orientation)] if p.orientation else []
    steps += [
        SetChamber(setpoint_c=p.start_c),
        Soak(duration_s=p.soak_h * 3600.0),
        GyroPower(on=True),
        Soak(duration_s=p.warmup_min * 60.0, record={**rec, "phase": "warmup"}),
        Ramp(target_c=p.end_c, rate_c_per_min=p.rate_c_per_min, record={**rec, "phase": "ramp"}),
        Soak(duration_s=p.final_hold_min * 60.0, record={**rec, "phase": "cold_hold"}),
        GyroPower(on=False),
    ]
    if p.fit:
        steps.append(Fit(models=p.fit_models, options={"procedure": NAME}))
    return Plan(name=NAME, steps=steps, params=p.model_dump(mode="json"))

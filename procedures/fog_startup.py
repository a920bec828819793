"""S004 FOG IMU start-up at several temperatures; a second orientation is the validation set.

"Points -40, -25, -10, 5, 20, 35, 45, 60 C.  Soak fully at the first point and, once the gyros in
the IMU are at the set temperature, power the IMU and test for 2 h; power off, soak at the next
point, and so on.  Then change the IMU's position and repeat all points (group 2) to validate the
model."

"At temperature" is a wait-until-stable with the gyro probes within ``stable.probe_tol_c`` of the
set point and changing less than ``stable.probe_rate_c_per_min`` (or a fixed ``soak_h`` with
``settle="soak"``).  The gyro is off while soaking (a cold start is the point of the test).
Fits: stepwise polynomial and Delaunay interpolation (temperature, temperature rate).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from bench.engine import Fit, GyroPower, Orient, Plan, Record
from procedures.common import CelsiusPoints, Hours, Minutes, ModelList, StableParams, _Params, hold_at

NAME = "fog_startup"
DESCRIPTION = ("S004 FOG start-up: at -40, -25, -10, 5, 20, 35, 45, 60 C soak until the IMU is at "
               "temperature, power on, record 2 h, power off; repeated in a second orientation for validation")


class Params(_Params):
    points_c: CelsiusPoints = Field(default_factory=lambda: [-40.0, -25.0, -10.0, 5.0, 20.0, 35.0, 45.0, 60.0])
    orientations: list[str] = Field(default_factory=lambda: ["ENU", "NWU"], min_length=1, max_length=2)
    settle: Literal["soak", "stable"] = "stable"
    soak_h: Hours = 4.0
    stable: StableParams = StableParams(probe_tol_c=1.0)
    record_min: Minutes = 120.0
    fit_models: ModelList = Field(default_factory=lambda: ["fog_stepwise", "fog_delaunay"])


def build(params: Params | None = None) -> Plan:
    p = params or Params()
    steps: list = [GyroPower(on=False)]
    for group, orientation in zip(("model", "validation"), p.orientations):
        steps.append(Orient(code=orientation))
        for point in p.points_c:
            steps += hold_at(point, p.settle, p.soak_h, p.stable)
            steps += [GyroPower(on=True),
                      Record(duration_s=p.record_min * 60.0,
                             labels={"set": group, "temperature_c": point, "position": orientation}),
                      GyroPower(on=False)]
    validate = {"set": "validation"} if len(p.orientations) > 1 else None
    steps.append(Fit(models=p.fit_models, options={"procedure": NAME, "train": {"set": "model"},
                                                   "validate": validate}))
    return Plan(name=NAME, steps=steps, params=p.model_dump(mode="json"))

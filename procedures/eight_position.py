"""S000 3.2 static test: eight positions at 11 temperature points.

"Every 10 C from -40 to +60 C (11 points); at each point soak 4 h, then sample one minute in each of
the eight positions 东南地, 天南东, 西南天, 地南西, 西北地, 天北西, 东北天, 地北南; repeat the experiment
several times; fit the static temperature model (eq. 3) by least squares."

Positions are the codes ESD, USE, WSU, DSW, WND, UNW, ENU, DNE (x, y, z directions; the printed
eighth 地北南 is not right-handed, DNE is meant).  The table must reach all eight (mount the gyro
with y on the inner axis, see ``bench.devices.orientation.EIGHT_POSITION_GEOMETRY``): validation
refuses the plan otherwise.

``repetitions`` (default 1) repeats the eight-position sequence at each point.  The paper's "repeat
the experiment several times" is read as repeating the whole campaign (another run), so one pass
per point is the default: 11 x (4 h + 8 x 1 min) + table moves = about 45.6 h of bench time
(about 47 h with repetitions=2).  The gyro stays powered for the whole test.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from bench.engine import Fit, GyroPower, Orient, Plan, Record
from procedures.common import (MAX_POINTS, CelsiusPoints, Count, Hours, Minutes, ModelList, StableParams, _Params,
                               frange, hold_at)

NAME = "eight_position"
DESCRIPTION = ("S000 3.2 static eight-position test: -40..+60 C every 10 C, 4 h soak, 1 min in each of "
               "ESD USE WSU DSW WND UNW ENU DNE; static model fit")
EIGHT_POSITIONS = ["ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE"]


class Params(_Params):
    points_c: CelsiusPoints = Field(default_factory=lambda: frange(-40.0, 60.0, 10.0))
    soak_h: Hours = 4.0
    settle: Literal["soak", "stable"] = "soak"
    stable: StableParams = StableParams()
    positions: list[str] = Field(default_factory=lambda: list(EIGHT_POSITIONS), min_length=1, max_length=MAX_POINTS)
    record_min: Minutes = 1.0
    repetitions: Count = Field(1, ge=1, le=100)
    fit_models: ModelList = Field(default_factory=lambda: ["static"])


def build(params: Params | None = None) -> Plan:
    p = params or Params()
    steps: list = [Orient(code=p.positions[0]), GyroPower(on=True)]
    for point in p.points_c:
        steps += hold_at(point, p.settle, p.soak_h, p.stable)
        for rep in range(1, p.repetitions + 1):
            for position in p.positions:
                steps.append(Orient(code=position))
                steps.append(Record(duration_s=p.record_min * 60.0,
                                    labels={"temperature_c": point, "position": position, "repetition": rep}))
    steps += [GyroPower(on=False),
              Fit(models=p.fit_models, options={"procedure": NAME, "group_by": ["temperature_c", "position"]})]
    return Plan(name=NAME, steps=steps, params=p.model_dump(mode="json"))

"""Plan and step models: what a procedure asks the bench to do, as plain serialisable data.

A ``Plan`` is a name, an ordered list of steps and optional plan-level constraints.  It is a
pydantic model so it round-trips through JSON (the engine stores it with the run and rebuilds it
on ``resume``) and so the API can show its schema.

Steps (the ``kind`` field discriminates):

- ``SetChamber(setpoint_c)``: write the chamber static set point (a jump); holding there is
  done by a following ``Soak``/``WaitStable``.
- ``Ramp(target_c, rate_c_per_min)``: ramp the chamber at a fixed rate; optionally keep going
  ``until_probes_c`` (every gyro probe at that temperature, e.g. S002 "until every gyro reads 50 C").
- ``Soak(duration_s)``: fixed bench-time hold.
- ``WaitStable(...)``: chamber within +-tol of its set point and every gyro probe changing less
  than ``probe_rate_c_per_min`` for ``stable_s`` (optionally every probe within ``probe_tol_c`` of
  the set point), bounded by ``timeout_s``.
- ``Orient(code)``: move the two-axis table so the gyro axes point as the three-letter code says.
- ``TableRate(axis, rate_dps)``: rate mode on one axis.
- ``GyroPower(on)``: power supply output on/off.
- ``Record(duration_s, labels)``: a fixed hold whose data is labelled as a segment.
- ``Fit(models)``: the final model fit (through the engine's fit hook).

``Soak``, ``Ramp`` and ``WaitStable`` take an optional ``record`` dict: when given, the step's data
is labelled as a segment too (so a ramp can be recorded while it runs, S000 3.3).  Every step may
carry ``part`` (e.g. "model" / "validation") used by plan constraints, and a free ``note``.
"""
from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field

LabelValue = Union[str, int, float, bool]
Labels = dict[str, LabelValue]


class _Step(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    note: str = ""
    part: str | None = None

    def describe(self) -> str:  # pragma: no cover - overridden
        return self.kind  # type: ignore[attr-defined]


class SetChamber(_Step):
    kind: Literal["set_chamber"] = "set_chamber"
    setpoint_c: float

    def describe(self) -> str:
        return f"chamber set point {self.setpoint_c:g} C"


class Ramp(_Step):
    kind: Literal["ramp"] = "ramp"
    target_c: float
    rate_c_per_min: float
    until_probes_c: float | None = None
    probe_tol_c: float = 0.25
    until_timeout_s: float = 3 * 3600.0
    record: Labels | None = None

    def describe(self) -> str:
        text = f"ramp to {self.target_c:g} C at {self.rate_c_per_min:g} C/min"
        if self.until_probes_c is not None:
            text += f" until every probe reads {self.until_probes_c:g} C"
        return text


class Soak(_Step):
    kind: Literal["soak"] = "soak"
    duration_s: float
    record: Labels | None = None

    def describe(self) -> str:
        return f"soak {self.duration_s / 60:g} min"


class WaitStable(_Step):
    kind: Literal["wait_stable"] = "wait_stable"
    tol_c: float = 1.0
    probe_rate_c_per_min: float | None = 0.05
    probe_tol_c: float | None = None
    rate_window_s: float = 300.0
    stable_s: float = 600.0
    timeout_s: float = 8 * 3600.0
    expected_s: float = 3600.0          # used only for duration estimates / ETA
    on_timeout: Literal["continue", "abort"] = "continue"
    record: Labels | None = None

    def describe(self) -> str:
        text = f"wait until stable (chamber +-{self.tol_c:g} C"
        if self.probe_rate_c_per_min is not None:
            text += f", probes < {self.probe_rate_c_per_min:g} C/min"
        if self.probe_tol_c is not None:
            text += f", probes within +-{self.probe_tol_c:g} C of set point"
        return text + f" for {self.stable_s / 60:g} min)"


class Orient(_Step):
    kind: Literal["orient"] = "orient"
    code: str
    timeout_s: float = 600.0

    def describe(self) -> str:
        return f"turntable to {self.code}"


class TableRate(_Step):
    kind: Literal["table_rate"] = "table_rate"
    axis: Literal["outer", "inner"]
    rate_dps: float

    def describe(self) -> str:
        return f"turntable {self.axis} axis rate {self.rate_dps:g} deg/s"


class GyroPower(_Step):
    kind: Literal["gyro_power"] = "gyro_power"
    on: bool

    def describe(self) -> str:
        return f"gyro power {'on' if self.on else 'off'}"


class Record(_Step):
    kind: Literal["record"] = "record"
    duration_s: float
    labels: Labels

    def describe(self) -> str:
        lab = ", ".join(f"{k}={v}" for k, v in self.labels.items())
        return f"record {self.duration_s / 60:g} min ({lab})"


class Fit(_Step):
    kind: Literal["fit"] = "fit"
    models: list[str]
    options: dict[str, Any] = Field(default_factory=dict)

    def describe(self) -> str:
        return f"fit {', '.join(self.models)}"


Step = Annotated[
    Union[SetChamber, Ramp, Soak, WaitStable, Orient, TableRate, GyroPower, Record, Fit],
    Field(discriminator="kind"),
]


def step_labels(step: Any) -> Labels | None:
    """Segment labels of a step, or None when the step does not record."""
    if isinstance(step, Record):
        return dict(step.labels)
    rec = getattr(step, "record", None)
    return dict(rec) if rec is not None else None


class WeakCorrelation(BaseModel):
    """Plan constraint (S001): the planned chamber set-point profiles of two parts of the plan
    must correlate weakly: |r| < max_abs_r.  See ``bench.engine.planning.part_correlation``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["weak_correlation"] = "weak_correlation"
    part_a: str
    part_b: str
    max_abs_r: float = 0.4
    resample_s: float = 60.0


class Plan(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    steps: list[Step]
    params: dict[str, Any] = Field(default_factory=dict)
    constraints: list[WeakCorrelation] = Field(default_factory=list)
    start_c: float = 25.0   # assumed chamber set point before the first step (estimates only)

    def to_json(self) -> dict[str, Any]:
        return self.model_dump(mode="json")

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "Plan":
        return cls.model_validate(data)

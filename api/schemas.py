"""Request bodies of the API.  Every body refuses unknown fields (``extra="forbid"``) and checks its
ranges, so a typo is an error rather than a silently ignored setting."""
from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from bench.fit.formula import MAX_FORMULA_CHARS          # one limit for the CLI and the API
from procedures import PROCEDURE_MODULES


MAX_ROW_ID = 2**53 - 1    # ids beyond are refused (422), never looked up (exact in JSON numbers; 64-bit keys hold it)
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="a stored id (1 .. 2^53-1)")]
BodyRowId = Annotated[int, Field(ge=1, le=MAX_ROW_ID)]
GyroPath = Annotated[str, Path(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$", description="gyro ID")]
ProcedureName = Literal[PROCEDURE_MODULES]

# a registered model name or a formula (bench.fit.formula grammar and limits)
MODEL_FORMAT = "gyrobench-model"
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="before")
    @classmethod
    def _no_bool_for_numbers(cls, data: Any) -> Any:
        """true/false is not a number: refused for every field that is not a flag (JSON 2.0 stays 2)."""
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if field is None or field.annotation is bool or name == "params":
                    continue
                items = value if isinstance(value, list) else [value]
                if any(isinstance(v, bool) for v in items):
                    raise ValueError(f"{name}: true/false given where a number or text is needed")
        return data


GYRO_IN_SLOT_PATTERN = r"^([A-Za-z0-9][A-Za-z0-9._-]{0,63}=)?[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"


class RunCreate(_Body):
    # exactly one of gyro_id / gyro_ids, said in the schema too
    model_config = ConfigDict(**_Body.model_config,
                              json_schema_extra={"oneOf": [{"required": ["gyro_id"]}, {"required": ["gyro_ids"]}]})

    procedure: ProcedureName = Field(..., description="a name from GET /procedures")
    # absent, never null: the schema's oneOf counts a present key (the default None is not validated)
    gyro_id: str = Field(  # type: ignore[assignment]
        None, pattern=ID_PATTERN,
        description="gyro serial / ID: 1-64 letters, digits, '.', '_' or '-' (one gyro; give this or gyro_ids)")
    gyro_ids: list[Annotated[str, Field(pattern=GYRO_IN_SLOT_PATTERN)]] = Field(  # type: ignore[assignment]
        None, min_length=1, max_length=64, description=(
            "several gyros in one chamber (a bench whose config lists gyro slots): each 'ID' (the next free "
            "slot) or 'SLOT=ID'; the run gets one run per gyro, listed under units"))
    bench: str = Field(..., pattern=ID_PATTERN, description="a bench name from GET /benches")
    params: dict[str, Any] = Field(default_factory=dict,
                                   description="procedure parameters; see GET /procedures for schema and defaults")
    start_at: dt.datetime | None = Field(None, description="scheduled start (ISO 8601 with a time zone); "
                                                           "the run waits in the queue until then")
    operator: str | None = Field(None, max_length=64, description="who starts the run (for the records)")

    @model_validator(mode="after")
    def _one_of(self) -> "RunCreate":
        if (self.gyro_id is None) == (self.gyro_ids is None):
            raise ValueError("give exactly one of gyro_id (one gyro) / gyro_ids (several gyros in one chamber)")
        return self

    @field_validator("start_at")
    @classmethod
    def _aware(cls, value: dt.datetime | None) -> dt.datetime | None:
        if value is not None and value.utcoffset() is None:
            raise ValueError("start_at needs a time zone, e.g. 2025-03-01T22:00:00+01:00 or ...Z")
        return value.astimezone(dt.timezone.utc) if value is not None else None


class FitCreate(_Body):
    model: str = Field(..., min_length=1, max_length=MAX_FORMULA_CHARS, json_schema_extra={"format": MODEL_FORMAT},
                       description="a model name (static, dynamic, patent37, hrg, fog_stepwise...) or a formula")
    run_ids: list[BodyRowId] = Field(..., min_length=1, max_length=20, description="training runs (same gyro)")
    validation_run_ids: list[BodyRowId] = Field(default_factory=list, max_length=20,
                                          description="held-out runs the report evaluates on")
    gyro_id: str | None = Field(None, pattern=ID_PATTERN, description="defaults to the runs' gyro")
    channels: list[Literal["x", "y", "z"]] | None = Field(None, min_length=1, max_length=3)
    latitude_deg: float | None = Field(None, ge=-90, le=90)
    accept: bool = Field(False, description="make this version the gyro's accepted coefficients (admin only)")

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        return _model_name(value)

    @field_validator("run_ids", "validation_run_ids")
    @classmethod
    def _positive(cls, value: list[int]) -> list[int]:
        bad = [v for v in value if v < 1]
        if bad:
            raise ValueError(f"run ids are positive integers, got {bad}")
        if len(set(value)) != len(value):
            raise ValueError("a run id is listed twice")
        return value


def _model_name(value: str) -> str:
    from bench.fit.catalog import check_model_name

    return check_model_name(value)


class CloseLoopCreate(_Body):
    model: str = Field(..., min_length=1, max_length=MAX_FORMULA_CHARS, json_schema_extra={"format": MODEL_FORMAT},
                       description="declared model: a linear model or a formula")
    train_run_id: BodyRowId
    validation_run_id: BodyRowId
    channels: list[Literal["x", "y", "z"]] | None = Field(None, min_length=1, max_length=3)
    latitude_deg: float | None = Field(None, ge=-90, le=90)

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        return _model_name(value)


DataStream = Literal["seconds", "frames", "probes", "telemetry"]
DataFormat = Literal["json", "csv"]

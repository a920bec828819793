"""Every model of the fitting module in one registry: the linear models of ``bench.fit.models`` plus the
HRG (S002) and FOG (S004) models.  Import ``fit_model`` / ``predict`` from here."""
from __future__ import annotations

import numpy as np

from bench.fit import fog, hrg, prep
from bench.fit.base import Dataset, FitResult
from bench.fit.models import compensate, fit_model, predict, register_model, registered_models

def _freq_needs(channel: str, opts: dict) -> list[str]:      # hrg_reverse / hrg_forward: no gyro output needed
    probe = opts.get("reference") or opts.get("probe")
    return [f"freq_{channel}"] + ([probe if str(probe).startswith("temp_") else f"temp_{probe}"] if probe else [])


def _hrg_needs(channel: str, opts: dict) -> list[str]:
    source = opts.get("temperature_source", "freq")
    return [f"gyro_{channel}"] + ([f"freq_{channel}"] if source == "freq" and not opts.get("reverse") else [])


def _thermal_needs(channel: str, opts: dict) -> list[str]:
    probe = opts.get("probe")
    return [f"gyro_{channel}"] + ([probe if str(probe).startswith("temp_") else f"temp_{probe}"] if probe else [])


for _name, _fit, _predict, _desc, _needs in (
        ("hrg", hrg.fit_hrg, hrg.predict_hrg, "S002 eq 7 six-term bias model, least squares", _hrg_needs),
        ("hrg_pso", hrg.fit_hrg_pso, hrg.predict_hrg, "S002 eq 7 by particle swarm (paper settings), LS cost beside",
         _hrg_needs),
        ("hrg_reverse", hrg.fit_hrg_reverse, hrg.predict_hrg_reverse, "S002 reverse cubic T(f) (frequency thermometer)",
         _freq_needs),
        ("hrg_forward", hrg.fit_hrg_forward, hrg.predict_hrg_forward, "S002 forward cubic f(T)", _freq_needs),
        ("fog_stepwise", fog.fit_fog_stepwise, fog.predict_fog_stepwise, "S004 eq 6 stepwise regression (HAC tests)",
         _thermal_needs),
        ("fog_delaunay", fog.fit_fog_delaunay, fog.predict_fog_delaunay,
         "S004 2-D Delaunay interpolation over (T, dT/dt)", _thermal_needs)):
    if _name not in registered_models():
        register_model(_name, _fit, _predict, description=_desc, needs=_needs)

NAMED_MODELS = tuple(registered_models())


def check_model_name(name: str) -> str:
    """``name`` if it is a registered model or a formula within the formula limits, else ValueError naming
    why (the same check for procedure parameters, the API and the CLI)."""
    from bench.fit.formula import FormulaError, parse_formula

    if name.strip() in NAMED_MODELS:
        return name.strip()
    try:
        parse_formula(name)
    except FormulaError as exc:
        raise ValueError(f"{name[:60]!r} is neither a fit model ({', '.join(NAMED_MODELS)}) nor a valid formula: "
                         f"{str(exc).splitlines()[0]}") from None
    return name


def target_of(result: FitResult, data: Dataset) -> np.ndarray:
    """What the model predicts, measured on ``data``: the target column, less the Earth rate when the
    fit removed it."""
    y = np.asarray(data[result.target], dtype=float)
    er = (result.definition.get("earth_rate") or {})
    if er.get("earth_rate_removed") is True:
        axis = np.asarray(er.get("axis")) if er.get("axis") is not None else None
        y = y - prep.earth_rate_reading(data, result.channel, er.get("latitude_deg"), axis)
    return y


__all__ = ["check_model_name", "fit_model", "predict", "compensate", "target_of", "NAMED_MODELS"]

"""Test procedures (one module each): ``NAME``, ``DESCRIPTION``, a pydantic ``Params`` model whose
defaults follow the seed papers, and ``build(params) -> bench.engine.Plan``."""
from __future__ import annotations

import importlib
from types import ModuleType

PROCEDURE_MODULES = ("eight_position", "thermal_ramp", "rate_cycle", "hrg_calibration", "fog_startup")


def get(name: str) -> ModuleType:
    if name not in PROCEDURE_MODULES:
        raise KeyError(f"unknown procedure {name!r}; known: {', '.join(PROCEDURE_MODULES)}")
    return importlib.import_module(f"procedures.{name}")


def all_procedures() -> dict[str, ModuleType]:
    return {name: get(name) for name in PROCEDURE_MODULES}


def check_duration(summary: dict) -> None:
    """Refuse a plan whose estimated bench time (``plan_summary``) exceeds ``MAX_PLAN_DAYS``."""
    from bench.errors import PlanError
    from procedures.common import MAX_PLAN_DAYS

    total = float(summary.get("total_bench_s") or 0.0)
    if not total <= MAX_PLAN_DAYS * 86400.0:
        raise PlanError(f"plan {summary.get('name')!r} would take {total / 86400.0:.1f} days of bench time; "
                        f"a plan may take at most {MAX_PLAN_DAYS:g} days")

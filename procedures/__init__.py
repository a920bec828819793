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

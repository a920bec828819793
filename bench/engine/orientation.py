"""Orientation codes as the engine sees them.

A code is three letters from E W N S U D giving the directions of the gyro's x, y and z axes in the
local level frame (S000 3.2: 东南地 = "ESD" means x East, y South, z Down); the one definition of a
valid code is ``bench.signal.geometry.validate_code``.

The table angles for a code come from the turntable helper's solver
``bench.devices.orientation.angles_for`` (raises ``OrientationError``, a ``BenchError``, when the
geometry cannot reach the code); it is imported lazily so the engine (and plan validation) does not
depend on the driver package being importable.
"""
from __future__ import annotations

from typing import Any

from bench.errors import PlanError
from bench.signal.geometry import OrientationError, validate_code


def orientation_problem(code: Any) -> str | None:
    """Why ``code`` is not a valid orientation code (``bench.signal.geometry.validate_code``), or None."""
    try:
        validate_code(code)
    except OrientationError as exc:
        return str(exc)
    return None


def check_orientation(code: str) -> str:
    try:
        return validate_code(code)
    except OrientationError as exc:
        raise PlanError(str(exc)) from None


def solve_angles(code: str, geometry: Any) -> tuple[float, float]:
    """(outer_deg, inner_deg) for ``code`` from the turntable helper's solver."""
    from bench.devices import orientation as solver  # lazy: driver package is optional here

    return solver.angles_for(check_orientation(code), geometry)


def solver_available() -> bool:
    try:
        from bench.devices import orientation as solver  # noqa: F401
    except ImportError:
        return False
    return hasattr(solver, "angles_for")

"""Orientation codes as the engine sees them.

A code is three letters from E W N S U D giving the directions of the gyro's x, y and z axes in the
local level frame (S000 3.2: 东南地 = "ESD" means x East, y South, z Down).  A valid code is a
right-handed triad: x cross y = z.  (The paper prints its eighth position as 地北南 = "DNS", which
is not right-handed; "DNE" is meant.)

The table angles for a code come from the turntable helper's solver
``bench.devices.orientation.angles_for`` (raises ``OrientationError``, a ``BenchError``, when the
geometry cannot reach the code); it is imported lazily so the engine (and plan validation) does not
depend on the driver package being importable.
"""
from __future__ import annotations

from typing import Any

from bench.errors import PlanError

DIRECTIONS: dict[str, tuple[int, int, int]] = {
    "E": (1, 0, 0), "W": (-1, 0, 0),
    "N": (0, 1, 0), "S": (0, -1, 0),
    "U": (0, 0, 1), "D": (0, 0, -1),
}


def _cross(a: tuple[int, int, int], b: tuple[int, int, int]) -> tuple[int, int, int]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def orientation_problem(code: Any) -> str | None:
    """Why ``code`` is not a valid orientation code, or None when it is."""
    if not isinstance(code, str) or len(code) != 3:
        return f"orientation code must be three letters from EWNSUD, got {code!r}"
    code = code.upper()
    bad = [c for c in code if c not in DIRECTIONS]
    if bad:
        return f"orientation code {code!r} has letters {''.join(bad)!r} not in EWNSUD"
    x, y, z = (DIRECTIONS[c] for c in code)
    if _cross(x, y) != z:
        return (f"orientation code {code!r} is not a right-handed triad "
                f"(x={code[0]} cross y={code[1]} is not z={code[2]})")
    return None


def check_orientation(code: str) -> str:
    problem = orientation_problem(code)
    if problem:
        raise PlanError(problem)
    return code.upper()


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

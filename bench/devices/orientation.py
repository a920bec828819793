"""The two-axis table angles that realise a gyro orientation code.

Orientation codes, their validation and geometry (``validate_code``, ``code_matrix``,
``EIGHT_POSITIONS``, ...) are defined in ``bench.signal.geometry`` and re-exported here for the
drivers and procedures.

Table model (``TurntableGeometry`` in bench/config.py; sign convention of this module: a positive
angle is a right-handed rotation about the configured axis vector; negate a vector to flip a
table's sense):

    body_to_level(outer, inner) = Rot(outer_axis, outer) @ Rot(inner_axis, inner) @ M

``outer_axis`` is expressed in the level frame, ``inner_axis`` in the outer-gimbal frame (it turns
with the outer axis) and ``M`` (from ``mounting``) holds the body axes in the inner-gimbal frame at
zero angles.  Columns of the result are the body x, y, z axes in ENU.

Reachability: the body axis lying along the inner axis stays horizontal whatever the angles when
the outer axis is vertical.  In all eight positions the body y axis is horizontal (South or
North), so the gyro must be mounted with y along the inner axis.  The default config geometry
(inner axis along East at rest, mounting ENU: x along the inner axis) reaches only ESD, WSU, WND
and ENU.  ``EIGHT_POSITION_GEOMETRY`` (inner axis along North at rest, mounting ENU) reaches all
eight: outer 0 deg gives y North (ENU, DNE, WND, UNW at inner 0, 90, 180, -90) and outer 180 deg
gives y South (WSU, DSW, ESD, USE).
"""
from __future__ import annotations

import math

import numpy as np

from bench.config import TurntableGeometry
from bench.interfaces import Turntable
from bench.signal.geometry import (  # noqa: F401  (codes and their geometry live in bench.signal)
    CHINESE_DIRECTIONS,
    DIRECTIONS,
    EIGHT_POSITIONS,
    SEED_EIGHT_POSITION_NAMES,
    OrientationError,
    all_codes,
    as_rotation,
    code_from_chinese,
    code_matrix,
    nearest_code,
    rotation_about,
    rotation_angle_deg,
    unit_vector,
    validate_code,
)

EIGHT_POSITION_GEOMETRY = TurntableGeometry(outer_axis=(0.0, 0.0, 1.0), inner_axis=(0.0, 1.0, 0.0),
                                            mounting="ENU")


# geometry ----------------------------------------------------------------------------------------
def check_geometry(geometry: TurntableGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit outer axis, unit inner axis, mounting matrix; ``OrientationError`` if unusable."""
    outer = unit_vector(geometry.outer_axis, "turntable geometry outer_axis")
    inner = unit_vector(geometry.inner_axis, "turntable geometry inner_axis")
    if np.linalg.norm(np.cross(outer, inner)) < 1e-6:
        raise OrientationError(f"turntable geometry: outer_axis {geometry.outer_axis} and inner_axis "
                               f"{geometry.inner_axis} are parallel; two parallel axes cannot orient a gyro")
    try:
        mounting = code_matrix(geometry.mounting)
    except OrientationError as exc:
        raise OrientationError(f"turntable geometry mounting: {exc}") from None
    return outer, inner, mounting


def body_to_level(outer_deg: float, inner_deg: float, geometry: TurntableGeometry) -> np.ndarray:
    """3x3 rotation, columns = body x, y, z axes in the level frame (E, N, U)."""
    outer, inner, mounting = check_geometry(geometry)
    return rotation_about(outer, outer_deg) @ rotation_about(inner, inner_deg) @ mounting


def code_at(outer_deg: float, inner_deg: float, geometry: TurntableGeometry) -> tuple[str, float]:
    """Nearest code at these angles and how far (deg) the real orientation is from it."""
    return nearest_code(body_to_level(outer_deg, inner_deg, geometry))


def angles_for(code: str, geometry: TurntableGeometry) -> tuple[float, float]:
    """(outer_deg, inner_deg) in (-180, 180] realising ``code``; ``OrientationError`` if unreachable."""
    norm = validate_code(code)
    check_geometry(geometry)
    if not _reachable(norm, geometry):
        reachable = ", ".join(reachable_codes(geometry))
        raise OrientationError(
            f"orientation {norm!r} is not reachable with outer_axis={geometry.outer_axis}, "
            f"inner_axis={geometry.inner_axis}, mounting={geometry.mounting!r}: the body axis on the inner "
            f"axis would have to leave the cone around the outer axis. Reachable: {reachable}. "
            f"Mount the gyro so that the axis that stays horizontal in all wanted positions lies on the "
            f"inner axis (see EIGHT_POSITION_GEOMETRY)")
    return angles_for_matrix(code_matrix(norm), geometry)


def angles_for_matrix(body_to_level_matrix: np.ndarray, geometry: TurntableGeometry) -> tuple[float, float]:
    """(outer_deg, inner_deg) in (-180, 180] with ``body_to_level(outer, inner) == matrix``.

    Solve Rot(o, a) Rot(i, b) = T with T = C M^T.  Rot(i, b) leaves i fixed, so Rot(o, a) i = T i
    fixes a (rotate i about o onto T i; possible only if both make the same angle with o); then
    Rot(i, b) = Rot(o, a)^T T gives b.  The product is checked against T at the end.  The solution
    is unique (mod 360 deg) because the axes are not parallel.
    """
    c = as_rotation(body_to_level_matrix, "body-to-level matrix")
    outer, inner, mounting = check_geometry(geometry)
    target = c @ mounting.T
    v = target @ inner
    if abs(float(outer @ inner) - float(outer @ v)) > 1e-6:
        raise OrientationError(f"orientation not reachable with geometry {geometry}: the inner axis would "
                               f"have to make a different angle with the outer axis")
    a = _angle_between_about(outer, inner, v)
    rest = rotation_about(outer, a).T @ target
    p = _perpendicular(inner)
    b = _angle_between_about(inner, p, rest @ p)
    if not np.allclose(rotation_about(outer, a) @ rotation_about(inner, b), target, atol=1e-7):
        raise OrientationError(f"no exact table angles found for this orientation with geometry {geometry}")
    return _wrap180(a), _wrap180(b)


def reachable_codes(geometry: TurntableGeometry) -> list[str]:
    """All valid codes this geometry can realise."""
    return [code for code in all_codes() if _reachable(code, geometry)]


def _reachable(code: str, geometry: TurntableGeometry) -> bool:
    outer, inner, mounting = check_geometry(geometry)
    v = code_matrix(code) @ mounting.T @ inner
    return abs(float(outer @ inner) - float(outer @ v)) <= 1e-6


# helpers -----------------------------------------------------------------------------------------
def _angle_between_about(axis: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
    """Signed angle (deg) turning ``start`` into ``end`` about ``axis`` (components along it ignored)."""
    s = start - (axis @ start) * axis
    e = end - (axis @ end) * axis
    return math.degrees(math.atan2(float(axis @ np.cross(s, e)), float(s @ e)))


def _perpendicular(axis: np.ndarray) -> np.ndarray:
    trial = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = np.cross(axis, trial)
    return p / np.linalg.norm(p)


def _wrap180(deg: float) -> float:
    wrapped = -((-deg + 180.0) % 360.0 - 180.0)  # (-180, 180]
    rounded = round(wrapped, 9)
    if rounded == -180.0:
        return 180.0
    return 0.0 if rounded == 0 else rounded


def move_to_orientation(table: Turntable, code: str, geometry: TurntableGeometry) -> tuple[float, float]:
    """Move ``table`` (any ``Turntable``) so the gyro sits in ``code``; returns (outer, inner) deg.

    Both axes are commanded before waiting so they travel together (drivers whose ``move_to``
    accepts ``wait=False``); otherwise they move one after the other.
    """
    outer_deg, inner_deg = angles_for(code, geometry)
    moves = ((geometry.outer_axis_number, outer_deg), (geometry.inner_axis_number, inner_deg))
    try:
        for axis, deg in moves:
            table.move_to(axis, deg, wait=False)  # type: ignore[call-arg]
    except TypeError:
        pass
    for axis, deg in moves:
        table.move_to(axis, deg)
    return outer_deg, inner_deg

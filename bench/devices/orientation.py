"""Gyro orientation codes and the two-axis table angles that realise them.

Orientation code: three letters from ``E W N S U D``, the level-frame (East, North, Up) directions
of the gyro body x, y and z axes.  "ESD" = x East, y South, z Down.  A code is valid only if the
three directions form a right-handed orthonormal triad (x cross y = z).

Eight-position test (seed 000, section 3.2, RLG thermal calibration): 东南地 ESD, 天南东 USE,
西南天 WSU, 地南西 DSW, 西北地 WND, 天北西 UNW, 东北天 ENU and the eighth printed 地北南 (D N S,
not right-handed: x Down and z South with y North gives x cross y = East); the position meant
is DNE (地北东).  ``EIGHT_POSITIONS`` holds the corrected list.

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

import functools
import itertools
import math

import numpy as np

from bench.config import TurntableGeometry
from bench.errors import BenchError
from bench.interfaces import Turntable

DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "E": (1.0, 0.0, 0.0), "W": (-1.0, 0.0, 0.0),
    "N": (0.0, 1.0, 0.0), "S": (0.0, -1.0, 0.0),
    "U": (0.0, 0.0, 1.0), "D": (0.0, 0.0, -1.0),
}
CHINESE_DIRECTIONS = {"东": "E", "西": "W", "南": "S", "北": "N", "天": "U", "地": "D"}

EIGHT_POSITIONS: tuple[str, ...] = ("ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")
# As printed in seed 000 section 3.2 -> code used here (the eighth is a misprint, see docstring).
SEED_EIGHT_POSITION_NAMES: dict[str, str] = {
    "东南地": "ESD", "天南东": "USE", "西南天": "WSU", "地南西": "DSW",
    "西北地": "WND", "天北西": "UNW", "东北天": "ENU", "地北南": "DNE",
}

EIGHT_POSITION_GEOMETRY = TurntableGeometry(outer_axis=(0.0, 0.0, 1.0), inner_axis=(0.0, 1.0, 0.0),
                                            mounting="ENU")

_TOL = 1e-9


class OrientationError(BenchError, ValueError):
    """Invalid orientation code or geometry, or a code the table cannot reach."""


# codes -------------------------------------------------------------------------------------------
def validate_code(code: str) -> str:
    """Return the upper-case code or raise ``OrientationError`` naming it and the reason."""
    if not isinstance(code, str):
        raise OrientationError(f"orientation code must be a string, got {code!r}")
    norm = code.strip().upper()
    if len(norm) != 3 or any(ch not in DIRECTIONS for ch in norm):
        raise OrientationError(f"orientation code {code!r}: need three letters from E W N S U D "
                               f"(body x, y, z directions)")
    vecs = [np.array(DIRECTIONS[ch]) for ch in norm]
    axes = [int(np.flatnonzero(v)[0]) for v in vecs]
    if len(set(axes)) != 3:
        raise OrientationError(f"orientation code {code!r}: two body axes point along the same "
                               f"level axis (not orthogonal: they must point along three different ENU axes)")
    if not np.allclose(np.cross(vecs[0], vecs[1]), vecs[2]):
        should = _letter(np.cross(vecs[0], vecs[1]))
        raise OrientationError(f"orientation code {code!r} is not right-handed (a left-handed frame): with x={norm[0]}, "
                               f"y={norm[1]} the z axis is {should}, so the code would be "
                               f"{norm[:2] + should!r}")
    return norm


def code_from_chinese(name: str) -> str:
    """'东南地' -> 'ESD' (validated; the seed's misprint 地北南 is refused like any invalid code)."""
    try:
        letters = "".join(CHINESE_DIRECTIONS[ch] for ch in name.strip())
    except KeyError as exc:
        raise OrientationError(f"orientation name {name!r}: unknown direction character {exc.args[0]!r} "
                               f"(use 东西南北天地)") from None
    return validate_code(letters)


def code_matrix(code: str) -> np.ndarray:
    """3x3 matrix whose columns are the body x, y, z axes (in ENU) for ``code``."""
    norm = validate_code(code)
    return np.column_stack([DIRECTIONS[ch] for ch in norm])


@functools.lru_cache(maxsize=None)
def all_codes() -> tuple[str, ...]:
    """The 24 valid (right-handed) orientation codes."""
    codes = []
    for letters in itertools.product(DIRECTIONS, repeat=3):
        try:
            codes.append(validate_code("".join(letters)))
        except OrientationError:
            pass
    return tuple(codes)


def nearest_code(matrix: np.ndarray) -> tuple[str, float]:
    """Closest code to a body-to-level rotation and the rotation angle (deg) between them."""
    m = _as_rotation(matrix, "matrix")
    best, best_angle = "", math.inf
    for code in all_codes():
        angle = rotation_angle_deg(code_matrix(code).T @ m)
        if angle < best_angle:
            best, best_angle = code, angle
    return best, best_angle


def rotation_angle_deg(rotation: np.ndarray) -> float:
    cos = (float(np.trace(rotation)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


# geometry ----------------------------------------------------------------------------------------
def rotation_about(axis: np.ndarray | tuple[float, float, float], angle_deg: float) -> np.ndarray:
    """Right-handed rotation matrix about unit vector ``axis`` (Rodrigues)."""
    k = _unit(axis, "rotation axis")
    a = math.radians(angle_deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)


def check_geometry(geometry: TurntableGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit outer axis, unit inner axis, mounting matrix; ``OrientationError`` if unusable."""
    outer = _unit(geometry.outer_axis, "turntable geometry outer_axis")
    inner = _unit(geometry.inner_axis, "turntable geometry inner_axis")
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
    c = _as_rotation(body_to_level_matrix, "body-to-level matrix")
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
def _unit(vec: np.ndarray | tuple[float, float, float], what: str) -> np.ndarray:
    arr = np.asarray(vec, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise OrientationError(f"{what}: need three finite numbers, got {vec!r}")
    n = float(np.linalg.norm(arr))
    if n < 1e-9:
        raise OrientationError(f"{what}: zero vector")
    return arr / n


def _as_rotation(matrix: np.ndarray, what: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=float)
    if m.shape != (3, 3) or not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise OrientationError(f"{what}: not a 3x3 proper rotation matrix")
    return m


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


def _letter(vec: np.ndarray) -> str:
    for letter, d in DIRECTIONS.items():
        if np.allclose(vec, d):
            return letter
    raise OrientationError(f"vector {vec} is not along a level axis")


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

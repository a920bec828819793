"""Orientation codes, their geometry, and the Earth rate a gyro reads in them.

Orientation code: three letters from ``E W N S U D``, the level-frame (East, North, Up) directions of
the gyro body x, y and z axes.  "ESD" = x East, y South, z Down.  A code is valid only if the three
directions form a right-handed orthonormal triad (x cross y = z).  ``DEFAULT_ORIENTATION`` = "NUE"
(S000's 北天东), the code assumed where a record names none.

Eight-position test (seed 000, section 3.2, RLG thermal calibration): 东南地 ESD, 天南东 USE,
西南天 WSU, 地南西 DSW, 西北地 WND, 天北西 UNW, 东北天 ENU and the eighth printed 地北南 (D N S,
not right-handed: x Down and z South with y North gives x cross y = East); the position meant
is DNE (地北东).  ``EIGHT_POSITIONS`` holds the corrected list.

Earth rate (calibration-notes sec. 3/6): Omega_ENU = Omega_ie [0, cos(lat), sin(lat)] in deg/h with
the WGS-84 Omega_ie; body axis i reads u_i . Omega, u_i = row i of ``orientation_axes(code)``.

The table angles that realise a code are the turntable's business (``bench.devices.orientation``).
"""
from __future__ import annotations

import functools
import itertools
import math

import numpy as np

from bench.errors import BenchError

EARTH_RATE_DPH = 7.2921158553e-5 * 180.0 / 3.141592653589793 * 3600.0  # WGS-84 Omega_ie, deg/h
DEFAULT_ORIENTATION = "NUE"

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

class OrientationError(BenchError, ValueError):
    """Invalid orientation code or geometry, or a code the table cannot reach."""


# codes ---------------------------------------------------------------------------------------------------
def validate_code(code: str) -> str:
    """Return the upper-case code or raise ``OrientationError`` naming it and the reason."""
    if not isinstance(code, str):
        raise OrientationError(f"orientation code must be a string, got {code!r}")
    norm = code.strip().upper()
    bad = "".join(ch for ch in norm if ch not in DIRECTIONS)
    if len(norm) != 3 or bad:
        letters = f" has letters {bad!r} not in EWNSUD" if bad else ""
        raise OrientationError(f"orientation code {code!r}{letters}: need three letters from E W N S U D "
                               f"(body x, y, z directions)")
    vecs = [np.array(DIRECTIONS[ch]) for ch in norm]
    axes = [int(np.flatnonzero(v)[0]) for v in vecs]
    if len(set(axes)) != 3:
        raise OrientationError(f"orientation code {code!r}: two body axes point along the same "
                               f"level axis (not orthogonal, so not a right-handed triad: they must point along three different ENU axes)")
    if not np.allclose(np.cross(vecs[0], vecs[1]), vecs[2]):
        should = direction_letter(np.cross(vecs[0], vecs[1]))
        raise OrientationError(f"orientation code {code!r} is not right-handed (not a right-handed triad but a left-handed frame): with x={norm[0]}, "
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
    m = as_rotation(matrix, "matrix")
    best, best_angle = "", math.inf
    for code in all_codes():
        angle = rotation_angle_deg(code_matrix(code).T @ m)
        if angle < best_angle:
            best, best_angle = code, angle
    return best, best_angle


def rotation_angle_deg(rotation: np.ndarray) -> float:
    cos = (float(np.trace(rotation)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def rotation_about(axis: np.ndarray | tuple[float, float, float], angle_deg: float) -> np.ndarray:
    """Right-handed rotation matrix about unit vector ``axis`` (Rodrigues)."""
    k = unit_vector(axis, "rotation axis")
    a = math.radians(angle_deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)



def unit_vector(vec: np.ndarray | tuple[float, float, float], what: str) -> np.ndarray:
    arr = np.asarray(vec, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise OrientationError(f"{what}: need three finite numbers, got {vec!r}")
    n = float(np.linalg.norm(arr))
    if n < 1e-9:
        raise OrientationError(f"{what}: zero vector")
    return arr / n


def as_rotation(matrix: np.ndarray, what: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=float)
    if m.shape != (3, 3) or not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise OrientationError(f"{what}: not a 3x3 proper rotation matrix")
    return m


def direction_letter(vec: np.ndarray) -> str:
    for letter, d in DIRECTIONS.items():
        if np.allclose(vec, d):
            return letter
    raise OrientationError(f"vector {vec} is not along a level axis")


def validate_canonical_code(code: str) -> str:
    """``code`` itself when it is written canonically (upper case, no blanks) and valid, else
    ``OrientationError`` (a ``ValueError``): the rule of stored data, CSV files and scenarios."""
    if not isinstance(code, str) or code != code.strip().upper():
        raise OrientationError(f"orientation {code!r}: need three upper-case letters from E W N S U D")
    return validate_code(code)


def orientation_axes(code: str) -> np.ndarray:
    """(3,3) array; row i = unit vector of body axis i (x, y, z) in ENU for canonical ``code``."""
    return code_matrix(validate_canonical_code(code)).T


def _unique_codes(codes: np.ndarray, default: str) -> tuple[np.ndarray, np.ndarray]:
    """The distinct codes (sorted) and each sample's index among them; empty codes mean ``default``.
    One position throughout, the common case, needs no sort, and several are sorted as fixed-width
    text, not as Python objects (measured on 36,000 samples: 9.3 ms -> 0.9 ms for one position,
    9.9 ms -> 5.3 ms for four)."""
    c = np.asarray(codes, dtype=object).reshape(-1)
    c = np.where(c == "", default, c)
    if c.size and bool(np.all(c == c[0])):
        return np.array([c[0]], dtype=object), np.zeros(c.size, dtype=np.intp)
    uniq, inverse = np.unique(c.astype(str), return_inverse=True)
    return uniq.astype(object), inverse.reshape(-1)


def orientation_axes_per_sample(codes: np.ndarray, default: str = DEFAULT_ORIENTATION) -> np.ndarray:
    """(n, 3, 3) array: [k, i, :] = body axis i of sample k in ENU; empty codes mean ``default``."""
    uniq, inverse = _unique_codes(codes, default)
    table = np.array([orientation_axes(str(code)) for code in uniq]).reshape(-1, 3, 3)
    return table[inverse]


def earth_rate_enu(latitude_deg: float) -> np.ndarray:
    """Earth rate in the level frame (E, N, U), deg/h, at ``latitude_deg`` (deg, north positive)."""
    lat = math.radians(latitude_deg)
    return EARTH_RATE_DPH * np.array([0.0, math.cos(lat), math.sin(lat)])


def earth_rate_body(code: str, latitude_deg: float) -> np.ndarray:
    """Earth rate read by body axes x, y, z (deg/h) in orientation ``code`` at ``latitude_deg``."""
    return orientation_axes(code) @ earth_rate_enu(latitude_deg)


def earth_rate_body_per_sample(codes: np.ndarray, latitude_deg: float,
                               default: str = DEFAULT_ORIENTATION) -> np.ndarray:
    """(n, 3) Earth rate on body x, y, z per sample (deg/h); empty codes mean ``default``."""
    uniq, inverse = _unique_codes(codes, default)
    table = np.array([earth_rate_body(str(code), latitude_deg) for code in uniq]).reshape(-1, 3)
    return table[inverse]

"""Orientation codes, two-axis solver and the eight-position set (seed 000 section 3.2)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench.config import TurntableGeometry
from bench.devices.orientation import (
    EIGHT_POSITION_GEOMETRY, EIGHT_POSITIONS, SEED_EIGHT_POSITION_NAMES, OrientationError, all_codes,
    angles_for, angles_for_matrix, body_to_level, code_at, code_from_chinese, code_matrix, nearest_code,
    reachable_codes, rotation_about, validate_code,
)

E, N, U = np.eye(3)


def test_there_are_24_right_handed_codes_and_the_eight_positions_are_among_them():
    codes = all_codes()
    assert len(codes) == 24 and len(set(codes)) == 24
    for code in codes:
        m = code_matrix(code)
        assert np.allclose(m.T @ m, np.eye(3)) and np.isclose(np.linalg.det(m), 1.0)
    assert set(EIGHT_POSITIONS) <= set(codes)
    assert len(set(EIGHT_POSITIONS)) == 8


def test_code_matrix_columns_are_body_axes_in_enu():
    m = code_matrix("ESD")
    assert np.allclose(m[:, 0], E) and np.allclose(m[:, 1], -N) and np.allclose(m[:, 2], -U)


@pytest.mark.parametrize("bad, reason", [
    ("DNS", "not orthogonal"), ("ENS", "not orthogonal"), ("EEU", "not orthogonal"),
    ("ESU", "not right-handed"), ("NEU", "not right-handed"), ("EN", "three letters"),
    ("ENX", "three letters"), ("", "three letters"),
])
def test_invalid_codes_are_refused_naming_the_code(bad, reason):
    with pytest.raises(OrientationError) as info:
        validate_code(bad)
    assert repr(bad) in str(info.value) and reason in str(info.value)


def test_left_handed_error_suggests_the_right_handed_code():
    with pytest.raises(OrientationError, match="'ESD'"):
        validate_code("ESU")


def test_lowercase_is_accepted():
    assert validate_code(" esd ") == "ESD"


def test_seed_chinese_names_and_the_misprinted_eighth():
    for name, code in SEED_EIGHT_POSITION_NAMES.items():
        if name == "地北南":
            with pytest.raises(OrientationError):
                code_from_chinese(name)   # D N S is not a rotation: the seed means DNE
        else:
            assert code_from_chinese(name) == code
    assert list(SEED_EIGHT_POSITION_NAMES.values()) == list(EIGHT_POSITIONS)
    assert code_from_chinese("地北东") == "DNE"


def test_rotation_sign_convention_is_right_handed():
    assert np.allclose(rotation_about(U, 90) @ E, N)
    assert np.allclose(rotation_about(N, 90) @ U, E)
    assert np.allclose(rotation_about(E, 90) @ N, U)


def test_body_to_level_composes_outer_then_inner_then_mounting():
    geometry = EIGHT_POSITION_GEOMETRY
    assert np.allclose(body_to_level(0, 0, geometry), np.eye(3))
    # outer 90 about Up: body x (East) goes North; the inner axis (North at rest) turns West.
    m = body_to_level(90, 0, geometry)
    assert np.allclose(m[:, 0], N)
    # inner +90 about that West-pointing axis (right-handed) takes body z from Up to North
    m = body_to_level(90, 90, geometry)
    assert np.allclose(m[:, 1], -E)                  # y stays on the inner axis (now West)
    assert np.allclose(m[:, 2], N)


def test_inner_axis_along_east_with_enu_mount_reaches_only_half_of_the_eight_positions():
    geometry = TurntableGeometry(inner_axis=(1.0, 0.0, 0.0), mounting="ENU")
    reachable = set(reachable_codes(geometry)) & set(EIGHT_POSITIONS)
    assert reachable == {"ESD", "WSU", "WND", "ENU"}
    with pytest.raises(OrientationError, match="'USE' is not reachable"):
        angles_for("USE", geometry)


@pytest.mark.parametrize("geometry", [
    EIGHT_POSITION_GEOMETRY,
    TurntableGeometry(inner_axis=(1.0, 0.0, 0.0), mounting="SEU"),   # inner along E, gyro y on it
    TurntableGeometry(inner_axis=(0.0, -1.0, 0.0), mounting="ENU"),
    TurntableGeometry(outer_axis=(0.0, 0.0, -1.0), inner_axis=(1.0, 0.0, 0.0), mounting="NWU"),
], ids=["eight-position default", "inner E, SEU mount", "inner -N", "outer down, NWU mount"])
def test_all_eight_positions_reachable_and_round_trip(geometry):
    for code in EIGHT_POSITIONS:
        outer, inner = angles_for(code, geometry)
        assert -180 < outer <= 180 and -180 < inner <= 180
        found, err = code_at(outer, inner, geometry)
        assert found == code and err < 1e-6


def test_eight_position_angles_are_the_expected_quarter_turns():
    expected = {"ENU": (0, 0), "DNE": (0, 90), "WND": (0, 180), "UNW": (0, -90),
                "WSU": (180, 0), "DSW": (180, 90), "ESD": (180, 180), "USE": (180, -90)}
    for code, (outer, inner) in expected.items():
        assert angles_for(code, EIGHT_POSITION_GEOMETRY) == (float(outer), float(inner))


def test_eight_positions_put_each_body_axis_up_and_down_for_gravity_projection():
    ups = {axis: set() for axis in range(3)}
    for code in EIGHT_POSITIONS:
        m = body_to_level(*angles_for(code, EIGHT_POSITION_GEOMETRY), EIGHT_POSITION_GEOMETRY)
        g_body = m.T @ np.array([0.0, 0.0, -1.0])          # gravity direction in body axes
        axis = int(np.argmax(np.abs(g_body)))
        ups[axis].add(round(float(g_body[axis])))
    assert ups[0] == {-1, 1} and ups[2] == {-1, 1}          # x and z see +g and -g; y stays level


@pytest.mark.parametrize("geometry", [
    EIGHT_POSITION_GEOMETRY, TurntableGeometry(),
    TurntableGeometry(outer_axis=(0.1, 0.2, 1.0), inner_axis=(1.0, 0.3, -0.2), mounting="UNW"),
], ids=["eight", "default", "skewed"])
def test_random_angle_pairs_round_trip_through_the_matrix(geometry):
    rng = np.random.default_rng(42)
    for outer, inner in rng.uniform(-180, 180, size=(200, 2)):
        m = body_to_level(outer, inner, geometry)
        assert np.allclose(m.T @ m, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(m), 1.0)
        back = angles_for_matrix(m, geometry)
        assert math.isclose(back[0], outer, abs_tol=1e-7) and math.isclose(back[1], inner, abs_tol=1e-7)


def test_nearest_code_reports_the_misalignment_angle():
    m = rotation_about(N, 3.0) @ code_matrix("ESD")
    code, err = nearest_code(m)
    assert code == "ESD" and math.isclose(err, 3.0, abs_tol=1e-9)


def test_bad_geometry_is_refused():
    with pytest.raises(OrientationError, match="parallel"):
        body_to_level(0, 0, TurntableGeometry(inner_axis=(0.0, 0.0, 2.0)))
    with pytest.raises(OrientationError, match="zero vector"):
        angles_for("ENU", TurntableGeometry(outer_axis=(0.0, 0.0, 0.0)))
    with pytest.raises(OrientationError, match="mounting"):
        angles_for("ENU", TurntableGeometry(mounting="DNS"))
    with pytest.raises(OrientationError, match="rotation"):
        angles_for_matrix(np.diag([1.0, 1.0, -1.0]), EIGHT_POSITION_GEOMETRY)


def test_bench_default_geometry_is_the_eight_position_one():
    assert TurntableGeometry() == EIGHT_POSITION_GEOMETRY

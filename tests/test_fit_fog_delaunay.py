"""FOG 2-D Delaunay interpolation model (seed 004 section 2.2)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.fog import DelaunaySurface, fit_fog_delaunay, predict_fog_delaunay, select_points

from tests.test_fit_fog_stepwise import startup_runs


def test_interpolates_inside_and_flags_outside_hull():
    train = startup_runs(11, rho_100s=0.5, sd=0.003)
    res = fit_fog_delaunay(train, "x", probe="t1")
    hull = np.asarray(res.validity["hull"])
    assert hull.ndim == 2 and hull.shape[1] == 2 and len(hull) >= 3
    json.dumps(res.to_json())                                    # storable as is
    # a second run with the same start temperatures: inside the hull nearly everywhere
    valid = startup_runs(12, rho_100s=0.5, sd=0.003)
    pred, flagged = predict_fog_delaunay(res, valid)
    assert np.all(np.isfinite(pred)) and pred.shape == valid["gyro_x"].shape
    ok = ~flagged
    assert ok.mean() > 0.5
    raw_spread = np.std(valid["gyro_x"][ok])
    assert np.std(valid["gyro_x"][ok] - pred[ok]) < 0.2 * raw_spread

    # far outside: 200 C hotter -> all flagged, finite, equal to values on the hull boundary
    hot = valid.with_columns(temp_t1=valid["temp_t1"] + 200.0)
    pred_hot, flagged_hot = predict_fog_delaunay(res, hot)
    assert flagged_hot.all() and np.all(np.isfinite(pred_hot))
    pts = np.asarray(res.definition["points"])
    assert pred_hot.min() >= pts[:, 2].min() - 1e-9 and pred_hot.max() <= pts[:, 2].max() + 1e-9


def test_outside_value_is_nearest_boundary_value():
    # plane z = 2T + 3r sampled on a square: on the boundary the clamp equals the plane at the
    # projected point, so a point left of the square gets the value at its horizontal projection
    T, r = np.meshgrid(np.linspace(0, 10, 6), np.linspace(-1, 1, 5))
    pts = np.column_stack([T.ravel(), r.ravel()])
    surf = DelaunaySurface(pts, (2 * T + 3 * r).ravel(), np.array([5.0, 0.0]), np.array([10.0, 2.0]))
    values, outside = surf(np.array([-5.0, 5.0, 5.0]), np.array([0.5, 0.2, 3.0]))
    assert outside.tolist() == [True, False, True]
    assert values == pytest.approx([0 + 1.5, 10 + 0.6, 10 + 3.0])


def test_point_selection_thins_slow_phase():
    T = np.concatenate([np.linspace(0, 10, 20), 10 + np.linspace(0, 0.2, 60)])
    rate = np.gradient(T, 100 / 60)
    y = T.copy()
    pts = select_points(T, rate, y, [slice(0, T.size)], stride=3, fast_fraction=0.1, grid=1000)
    assert 20 + 15 <= len(pts) <= 20 + 25


def test_degenerate_points_refused():
    data = Dataset({"time_s": np.arange(50) * 100.0, "temp_t1": np.full(50, 20.0), "gyro_x": np.zeros(50)})
    with pytest.raises(DataFormatError, match="fog_delaunay"):
        fit_fog_delaunay(data, "x", probe="t1")


def test_registry_mode_nan_blanks_flagged_only():
    train = startup_runs(13, rho_100s=0.5, sd=0.003, starts=(-10, 20, 50))
    res = fit_fog_delaunay(train, "x", probe="t1")
    hot_first_run = np.where(train["run"] == 0, 300.0, 0.0)
    probe = train.with_columns(temp_t1=train["temp_t1"] + hot_first_run)
    values, flagged = predict_fog_delaunay(res, probe, mode="nan")
    assert flagged[hot_first_run > 0].all() and flagged[hot_first_run == 0].mean() < 0.5
    assert np.isnan(values[flagged]).all() and np.isfinite(values[~flagged]).all()
    with pytest.raises(DataFormatError, match="mode"):
        predict_fog_delaunay(res, probe, mode="extrapolate")

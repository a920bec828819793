"""Versioned JSON export per gyro id, evaluated from the JSON alone."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit import models
from bench.fit.base import Dataset
from bench.fit.export import (build_export, evaluate_model_doc, latest_export, load_export, results_from_export,
                              save_export)
from tests.test_fit_core_synth import CAL_PROFILE, VAL_PROFILE, thermal_run


@pytest.fixture(scope="module")
def fitted():
    ds, _ = thermal_run(CAL_PROFILE, truth="dynamic", seed=41)
    return ds, [models.fit_model("static", ds, "x", probe="t1"),
                models.fit_model("dynamic", ds, "x", probe="t1", grad=("t1", "t2")),
                models.fit_model("t1 + (t1-t3)^2 + t1*dt1", ds, "x")]


def test_export_is_versioned_and_loads_back(fitted, tmp_path):
    _, results = fitted
    doc = build_export("KVH-0042", results, gyro_type="kvh_a", metrics={"std100_dph": 0.005})
    p1 = save_export(doc, tmp_path)
    p2 = save_export(doc, tmp_path)
    assert p1.name == "KVH-0042.r0001.json" and p2.name == "KVH-0042.r0002.json"
    assert latest_export(tmp_path, "KVH-0042") == p2
    back = load_export(p2)
    assert back["revision"] == 2 and back["schema_version"] == 1 and back["gyro_id"] == "KVH-0042"
    static = back["models"][0]
    assert static["model"] == "static" and static["coefficients"]["A0"] == results[0].coefficients["A0"]
    assert static["units"]["A2"] == "deg/h/C^2" and static["validity"]["tmax_c"] > 59
    assert [t["expr"] for t in static["evaluation"]["terms"]] == ["1", "(t1-25)", "(t1-25)^2", "(t1-25)^3"]
    json.loads(p2.read_text())   # strict JSON (no NaN)


def test_json_recipe_alone_reproduces_predict(fitted, tmp_path):
    _, results = fitted
    doc = load_export(save_export(build_export("G7", results), tmp_path))
    val, _ = thermal_run(VAL_PROFILE, truth="dynamic", seed=42)
    # push part of the run outside the fitted range to exercise clip + flag + hull
    val.columns["temp_t1"] = val["temp_t1"] + np.where(val.time > 20000, 15.0, 0.0)
    cols = {k: v for k, v in val.columns.items()}
    for res, mdoc in zip(results, doc["models"]):
        want, want_flag = models.predict(res, val)
        got, got_flag = evaluate_model_doc(mdoc, cols, val.time)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(got_flag, want_flag)
        assert want_flag.any()
    # stored coefficients applied through the registry give the same numbers
    for res, stored in zip(results, results_from_export(doc)):
        np.testing.assert_array_equal(models.predict(stored, val)[0], models.predict(res, val)[0])


def test_export_refuses_bad_ids_and_versions(fitted, tmp_path):
    _, results = fitted
    with pytest.raises(DataFormatError, match="gyro id"):
        build_export("../etc/passwd", results)
    doc = build_export("G8", results)
    path = save_export(doc, tmp_path)
    bad = json.loads(path.read_text())
    bad["schema_version"] = 99
    path.write_text(json.dumps(bad))
    with pytest.raises(DataFormatError, match="schema_version"):
        load_export(path)
    path.write_text("{not json")
    with pytest.raises(DataFormatError, match="line 1"):
        load_export(path)


def test_dataset_without_needed_column_is_refused(fitted):
    _, results = fitted
    ds = Dataset({"time_s": np.arange(3.0), "gyro_x": np.zeros(3), "temp_t9": np.zeros(3)})
    with pytest.raises(DataFormatError, match="temp_t1"):
        models.predict(results[0], ds)

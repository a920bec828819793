"""Scenario files (strict loading, clear errors, truth) and the offline generator's interface."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bench.errors import DataFormatError, PlanError
from bench.sim.offline import Profile, eight_position_profile, simulate
from bench.sim.physics import orientation_matrix
from bench.sim.scenario import SCENARIO_DIR, Scenario, parse_term


def _default_dict() -> dict:
    return json.loads((SCENARIO_DIR / "default.json").read_text())


@pytest.mark.parametrize("name", ["default", "hrg", "fog_effects"])
def test_builtin_scenarios_load(name):
    sc = Scenario.builtin(name)
    assert sc.name == name
    truth = sc.truth()
    assert set(truth["channels"]) == {"x", "y", "z"}
    assert (truth["hrg"] is not None) == (sc.gyro_type == "hrg")


def test_unknown_key_is_refused_with_its_path(tmp_path):
    data = _default_dict()
    data["thermal"]["nodes"]["t1"]["capacity"] = 5
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(DataFormatError) as err:
        Scenario.load(path)
    assert "thermal.nodes.t1.capacity" in str(err.value) and "unknown key" in str(err.value)
    assert str(path) in str(err.value)


def test_json_syntax_error_names_line_and_column(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{\n  "name": "x",\n  "gyro_type": "rlg",,\n}\n')
    with pytest.raises(DataFormatError) as err:
        Scenario.load(path)
    assert err.value.line == 3
    assert "line 3" in str(err.value) and "column 22" in str(err.value)


@pytest.mark.parametrize("mutate, words", [
    (lambda d: d["bias"]["x"]["terms"].update({"t9^2": 1.0}), ["bias.x.terms.t9^2", "'t9'"]),
    (lambda d: d["bias"]["x"]["terms"].update({"t1^9": 1.0}), ["power 9"]),
    (lambda d: d["bias"]["x"]["terms"].update({"t1+t2": 1.0}), ["cannot read factor"]),
    (lambda d: d["probes"].update({"t5": "nowhere"}), ["probes.t5", "nowhere"]),
    (lambda d: d["thermal"]["nodes"].update({"island": {"capacity_j_per_k": 10}}), ["island", "no thermal path"]),
    (lambda d: d["noise"].update({"w": {"arw_deg_rt_h": 0.1}}), ["noise", "'w'"]),
    (lambda d: d.update({"gyro_type": "hrg"}), ["hrg"]),
    (lambda d: d.update({"effects": {"warmup": {"tau_s": -1, "amplitude_dph": {}}}}), ["effects.warmup.tau_s"]),
])
def test_semantic_errors_name_the_place(mutate, words):
    data = _default_dict()
    mutate(data)
    with pytest.raises(DataFormatError) as err:
        Scenario.from_dict(data, source="test.json")
    for w in words:
        assert w in str(err.value)


def test_term_parser():
    names = {"t1", "t2", "core"}
    f = parse_term("(t1-t2)^2 * dcore", names)
    assert [(x.kind, x.a, x.b, x.power) for x in f] == [("grad", "t1", "t2", 2), ("rate", "core", None, 1)]
    assert parse_term("d(t1-core)", names)[0].kind == "grad_rate"
    with pytest.raises(ValueError, match="unknown temperature 'dx'"):
        parse_term("dx", names)


def test_truth_lists_terms_and_effects():
    truth = Scenario.builtin("fog_effects").truth()
    assert truth["channels"]["x"]["terms"]["dt2"] == 0.05
    assert truth["channels"]["x"]["t0_c"] == 25.0
    assert truth["effects"]["thermal_lag"]["tau_s"] == 600.0
    assert truth["effects"]["warmup"]["amplitude_dph"]["z"] == -0.25
    assert "unexplained" in truth["effects"]


def test_orientation_codes():
    assert np.allclose(orientation_matrix("NUE"), [[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    for bad in ("NUX", "NNE", "WSD", "nue"):
        with pytest.raises(PlanError):
            orientation_matrix(bad)


@pytest.mark.parametrize("segments, words", [
    ([("hold", 20.0)], ["segment 0", "2 argument"]),
    ([("ramp", 20.0, 0.0)], ["rate must be > 0"]),
    ([("soak", 20.0, 10)], ["unknown segment kind 'soak'"]),
    ([("hold", 20.0, 10), ("orient", "XYZ")], ["segment 1", "XYZ"]),
    ([("power", "maybe")], ["power must be"]),
    ([("power", "on")], ["needs at least one"]),
])
def test_profile_errors(segments, words):
    with pytest.raises(PlanError) as err:
        Profile.parse(segments)
    for w in words:
        assert w in str(err.value)


def test_dataset_columns_units_and_eight_positions():
    prof = eight_position_profile(25.0, 600.0, 60.0)
    ds = simulate("default", prof, 1.0, "NUE")
    assert len(ds) == 600 + 8 * 60
    assert ds.gyro_channels() == ["x", "y", "z"] and ds.temp_names() == ["t1", "t2", "t3", "t4"]
    for col in ("orientation", "power", "chamber_pv", "chamber_sp", "table_rate_dps"):
        assert col in ds
    assert list(ds["orientation"][[0, 600, -1]]) == ["NUE", "ESD", "DNE"]
    assert np.allclose(ds["temp_t1"] / 0.0625, np.round(ds["temp_t1"] / 0.0625))   # DS18B20 resolution
    assert ds.meta["gyro_type"] == "rlg" and float(ds.meta["latitude_deg"]) == 45.75
    # deg/h on the x channel, body x = North in NUE: ~ Earth rate * cos(lat) + bias
    assert 10.0 < np.mean(ds["gyro_x"][:600]) < 11.0
    hrg = simulate("hrg", [("hold", 20.0, 100)], 1.0)
    assert {"freq_x", "freq_y", "freq_z"} <= set(hrg.columns)


def test_day_of_one_second_data_is_generated():
    prof = [("hold", 25.0, 3600), ("ramp", -30.0, 1.0), ("hold", -30.0, 4 * 3600), ("ramp", 60.0, 0.5),
            ("hold", 60.0, 4 * 3600), ("ramp", 25.0, 1.0)]
    dur = 3600 + 55 * 60 + 4 * 3600 + 180 * 60 + 4 * 3600 + 35 * 60
    prof.append(("hold", 25.0, 86400 - dur))
    ds = simulate("fog_effects", prof, 1.0, "NUE")
    assert len(ds) == 86400
    assert np.isfinite(ds["temp_t1"]).all()

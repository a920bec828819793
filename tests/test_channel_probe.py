"""The channel's own probe (S000 eq 4: t_i for channel i): bench config and scenario map, run metadata
and the CSV line ``# channel_probes: x=t1,y=t2,z=t3``, ``bench.fit.base.channel_probe``, the named
models' default probe, the formula placeholders ``tc``/``dtc``, CLI, import and API."""
from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.config import BenchConfig
from bench.errors import DataFormatError
from bench.fit import prep
from bench.fit.base import Dataset, channel_probe, format_channel_probes, parse_channel_probes
from bench.fit.csvio import format_csv, parse_csv_text, write_csv
from bench.fit.effects import first_order_lag
from bench.fit.export import build_export, evaluate_model_doc
from bench.fit.formula import FormulaError, compile_formula, uses_channel_probe
from bench.fit.metrics import bias_stability
from bench.fit.models import fit_model, predict
from bench.sim.scenario import Scenario, parse_term
from tests.synth import chamber_profile

PROBE_TAUS = {"t1": 300.0, "t2": 1500.0, "t3": 3000.0, "t4": 5000.0}   # probes far apart during ramps
OWN = {"x": "t1", "y": "t2", "z": "t3"}
CUBIC = {"x": (0.10, 0.020, 4e-4, 6e-6), "y": (-0.20, -0.015, 3e-4, -5e-6), "z": (0.05, 0.010, -2e-4, 4e-6)}
RATE_DPH_PER_C_PER_MIN = {"x": 0.05, "y": -0.04, "z": 0.03}
NOISE_DPH = 0.02
DT = 10.0                                      # s between samples
NOISE_STD100 = NOISE_DPH / np.sqrt(100.0 / DT)   # std of 100-s means of the white noise
PROFILE = [("hold", 3600), ("ramp", 60, 1.0), ("hold", 5400), ("ramp", -20, 0.5), ("hold", 5400),
           ("ramp", 45, 2.0), ("hold", 3600), ("ramp", 0, 1.0), ("hold", 3600), ("ramp", 30, 0.25), ("hold", 3600)]
PROFILE_V = [("hold", 1800), ("ramp", -10, 0.7), ("hold", 7200), ("ramp", 55, 1.5), ("hold", 3600),
             ("ramp", 10, 0.3), ("hold", 5400), ("ramp", 40, 1.2), ("hold", 3600)]
runner = CliRunner()


def own_probe_run(profile=PROFILE, seed: int = 0, mapping: dict[str, str] | None = OWN) -> Dataset:
    """Channel i's bias is a cubic of its own probe t_i plus a dT_i/dt term; the probes lag the air by
    very different time constants, so t1 is a poor stand-in for t2 or t3."""
    rng = np.random.default_rng(seed)
    t, air = chamber_profile(profile, dt=DT)
    cols: dict[str, np.ndarray] = {"time_s": t, "chamber_pv": air}
    for name, tau in PROBE_TAUS.items():
        cols[f"temp_{name}"] = first_order_lag(air, t, tau)
    for ch, probe in OWN.items():
        temp = cols[f"temp_{probe}"]
        u = temp - 25.0
        a0, a1, a2, a3 = CUBIC[ch]
        rate = prep.rate_c_per_min(t, temp, prep.DEFAULT_RATE_WINDOW_S)
        cols[f"gyro_{ch}"] = (a0 + a1 * u + a2 * u ** 2 + a3 * u ** 3 + RATE_DPH_PER_C_PER_MIN[ch] * rate
                              + rng.normal(0, NOISE_DPH, t.size))
    meta: dict = {"gyro_id": "G-OWN", "notes": "synthetic: channel i depends on probe t_i"}
    if mapping is not None:
        meta["channel_probes"] = dict(mapping)
    return Dataset(cols, meta)


def std100(ds: Dataset, result) -> float:
    values, _ = predict(result, ds)
    resid = np.asarray(ds[result.target]) - values
    return bias_stability(ds.time, resid - np.nanmean(resid), 100.0)


# ------------------------------------------------------------------------------- map text and helper
def test_channel_probes_text_round_trips_and_bad_text_is_named():
    assert parse_channel_probes("x=t1, y = t2,z=t3") == OWN
    assert format_channel_probes(OWN) == "x=t1,y=t2,z=t3"
    for bad, what in (("x=t1,,y=t2", "empty item"), ("x:t1", "cannot read 'x:t1'"), ("x=t1,x=t2", "given twice"),
                      ("x=t 1", "cannot read")):
        with pytest.raises(ValueError, match=what):
            parse_channel_probes(bad)


def test_channel_probe_helper_uses_the_map_else_the_default_and_names_a_missing_probe():
    ds = own_probe_run(PROFILE[:2])
    assert [channel_probe(ds, ch) for ch in "xyz"] == ["t1", "t2", "t3"]
    unmapped = Dataset(ds.columns, {})
    assert [channel_probe(unmapped, ch) for ch in "xyz"] == ["t1", "t1", "t1"]     # the old default
    broken = Dataset({k: v for k, v in ds.columns.items() if k != "temp_t2"}, {"channel_probes": OWN})
    assert channel_probe(broken, "x") == "t1"
    with pytest.raises(DataFormatError, match=r"channel 'y': its probe 't2'.*no column temp_t2"):
        channel_probe(broken, "y")


# ----------------------------------------------------------------------------------------- CSV
def test_csv_carries_the_map_as_a_metadata_line_both_ways(tmp_path):
    ds = own_probe_run(PROFILE[:2])
    text = format_csv(ds)
    assert "# channel_probes: x=t1,y=t2,z=t3\n" in text
    back = parse_csv_text(text)
    assert back.meta["channel_probes"] == OWN and back.meta["gyro_id"] == "G-OWN"
    write_csv(back, tmp_path / "again.csv")
    assert parse_csv_text((tmp_path / "again.csv").read_text()).meta == back.meta
    bad = text.replace("x=t1,y=t2,z=t3", "x=t1;y=t2")
    with pytest.raises(DataFormatError, match=r"line 3.*cannot read 'x=t1;y=t2'"):
        parse_csv_text(bad, source="bad.csv")


# ------------------------------------------------------------------------------ bench config, scenario
def test_bench_config_validates_the_map_and_names_what_and_where(tmp_path):
    probes = {"probes": {"t1": "000000000001", "t2": "000000000002", "t3": "000000000003"}}
    ok = BenchConfig.model_validate({"gyro": {"channel_probes": OWN}, "probes": probes})
    assert ok.gyro.channel_probes == OWN
    assert ok.model_dump(mode="json")["gyro"]["channel_probes"] == OWN      # what a run's snapshot holds
    for gyro, match in (({"channel_probes": {"w": "t1"}}, r"gyro.channel_probes: unknown channel 'w'"),
                        ({"channel_probes": {"y": "t9"}}, r"gyro.channel_probes.y: 't9' is not a configured probe "
                                                          r"\(probes.probes: t1, t2, t3\)")):
        path = tmp_path / "bench.json"
        path.write_text(json.dumps({"gyro": gyro, "probes": probes}))
        with pytest.raises(DataFormatError, match=match) as err:
            BenchConfig.load(path)
        assert "bench.json" in str(err.value) and "Value error" not in str(err.value)


@pytest.mark.parametrize("name", ["default", "fog_effects", "hrg"])
def test_each_builtin_scenario_declares_the_probe_its_channels_depend_on(name):
    sc = Scenario.builtin(name)
    mapping = sc.channel_probe_map()
    assert sorted(mapping) == sorted(sc.channels)
    names = sc.temperature_names()
    for ch, probe in mapping.items():
        own_node = sc.node_of(sc.channel_nodes[ch])
        assert sc.node_of(probe) == own_node
        if name != "hrg":          # the HRG's bias follows its resonator, read through the case probe
            first = parse_term(next(iter(sc.bias[ch].terms)), names)[0]
            assert first.kind == "temp" and sc.node_of(first.a) == own_node, (ch, first)
    assert Scenario.builtin("default").channel_probe_map() == OWN
    assert Scenario.builtin("fog_effects").channel_probe_map() == {"x": "t2", "y": "t3", "z": "t1"}


def test_scenario_refuses_a_map_to_an_unknown_probe():
    data = Scenario.builtin("default").model_dump()
    data["channel_probes"] = {"x": "t1", "y": "nowhere"}
    with pytest.raises(DataFormatError, match=r"channel_probes.y: 'nowhere' is not a probe"):
        Scenario.from_dict(data)


def test_simulated_bench_config_and_offline_data_carry_the_scenario_map():
    from bench.sim.bench import SimulatedBench
    from bench.sim.offline import simulate

    sim = SimulatedBench(speed=3600.0, scenario="fog_effects").start()
    try:
        cfg = sim.config
        assert cfg.gyro.channel_probes == {"x": "t2", "y": "t3", "z": "t1"}
        assert set(cfg.gyro.channel_probes.values()) <= set(cfg.probes.probes)
    finally:
        sim.stop()
    ds = simulate("default", [("hold", 25.0, 600)], 2.0, seed=1)
    assert ds.meta["channel_probes"] == OWN


# --------------------------------------------------------------------------------------- named models
def test_named_models_use_the_channel_probe_and_an_explicit_probe_wins():
    train, validate = own_probe_run(seed=1), own_probe_run(PROFILE_V, seed=2)
    for ch in "xyz":
        res = fit_model("static", train, ch, bin_c=None)
        assert res.definition["probe"] == OWN[ch]
        assert res.definition["probe_source"] == "channel_probes metadata"
        assert res.coefficients["A1"] == pytest.approx(CUBIC[ch][1], abs=0.003)
    forced = fit_model("static", train, "y", probe="t1", bin_c=None)
    assert forced.definition["probe"] == "t1" and forced.definition["probe_source"] == "probe option"
    own = fit_model("static", train, "y", bin_c=None)
    assert std100(validate, forced) > 3 * std100(validate, own)
    dyn = fit_model("dynamic", train, "z")
    assert dyn.definition["probe"] == "t3" and dyn.definition["gradient"][0] == "t3"
    p37 = fit_model("patent37", train, "y")
    assert p37.definition["probe"] == "t2" and p37.definition["probes"] == ["t1", "t2", "t3", "t4"]
    assert p37.validity["hull_signals"] == ["temp:temp_t2", "rate:temp_t2"]
    unmapped = Dataset(train.columns, {})
    assert fit_model("static", unmapped, "y").definition["probe_source"].startswith("default")


def test_hrg_reference_probe_follows_the_map():
    from bench.fit.catalog import fit_model
    from bench.sim.offline import simulate

    prof = [("hold", -20.0, 3 * 3600), ("ramp", 50.0, 0.5), ("hold", 50.0, 3 * 3600)]
    ds = simulate("hrg", prof, 10.0, seed=5)
    assert ds.meta["channel_probes"] == OWN
    assert fit_model("hrg_reverse", ds, "y").target == "temp_t2"
    assert fit_model("hrg_reverse", ds, "y", reference="t4").target == "temp_t4"
    with pytest.raises(DataFormatError, match="choose the temperature probe"):
        fit_model("hrg_reverse", Dataset(ds.columns, {}), "y")


# ------------------------------------------------------------------------------------------ formulas
def test_tc_placeholders_resolve_per_channel_and_the_stored_model_is_self_contained():
    train, validate = own_probe_run(seed=3), own_probe_run(PROFILE_V, seed=4)
    formula = "(tc-25) + (tc-25)^2 + (tc-25)^3 + dtc"
    assert uses_channel_probe(formula) and uses_channel_probe("(tc-t4)") and not uses_channel_probe("t1 + dt1")
    for ch in "xyz":
        p = OWN[ch]
        res = fit_model(formula, train, ch)
        d = res.definition
        assert d["channel_probe"] == p and d["probe"] == p and d["formula"] == formula
        assert [t["expr"] for t in d["terms"]] == ["1", f"({p}-25)", f"({p}-25)^2", f"({p}-25)^3", f"d{p}"]
        assert list(res.coefficients) == ["intercept", "(tc-25)", "(tc-25)^2", "(tc-25)^3", "dtc"]
        assert res.coefficients["(tc-25)"] == pytest.approx(CUBIC[ch][1], abs=0.003)
        assert res.coefficients["dtc"] == pytest.approx(RATE_DPH_PER_C_PER_MIN[ch], abs=0.01)
        # predict on data that carries no map at all, and through the firmware export recipe
        bare = Dataset(validate.columns, {})
        values, flagged = predict(res, bare)
        doc = build_export("G-OWN", [res])["models"][0]
        recipe_values, recipe_flagged = evaluate_model_doc(doc, bare.columns, bare.time)
        assert np.allclose(values, recipe_values, atol=1e-9) and np.array_equal(flagged, recipe_flagged)
        assert std100(validate, res) < 2 * NOISE_STD100
        if ch != "x":        # one probe for every channel: much worse away from t1
            first = fit_model("(t1-25) + (t1-25)^2 + (t1-25)^3 + dt1", train, ch)
            assert std100(validate, first) > 5 * std100(validate, res)


def test_gradient_with_the_channel_probe_and_explicit_probe_option():
    ds = own_probe_run(PROFILE[:4], seed=5)
    res = fit_model("tc + (tc-t4) + (tc-25)*dtc", ds, "z")
    assert [t["expr"] for t in res.definition["terms"][1:]] == ["t3", "(t3-t4)", "(t3-25)*dt3"]
    res = fit_model("tc + (tc-t4)", ds, "z", probe="t2")
    assert [t["expr"] for t in res.definition["terms"][1:]] == ["t2", "(t2-t4)"]
    assert res.definition["probe_source"] == "probe option"


def test_tc_errors_name_the_reason():
    cols = ["time_s", "gyro_x", "temp_t1", "temp_t2"]
    with pytest.raises(FormulaError, match=r"'tc' stands for the channel's own probe.*at position 1"):
        compile_formula("tc + t2", cols)
    with pytest.raises(FormulaError, match=r"terms 't2' and 'tc' are the same term 't2'"):
        compile_formula("t2 + tc", cols, channel_probe="t2")
    with pytest.raises(FormulaError, match=r"'dtc': the channel's probe 't9' has no column temp_t9"):
        compile_formula("dtc", cols, channel_probe="t9")
    with pytest.raises(FormulaError, match=r"'\(tc-t2\)' is '\(t2-t2\)' \(the channel's probe is 't2'\): "
                                           r"identically zero"):
        compile_formula("tc + (tc-t2)", cols, channel_probe="t2")
    with pytest.raises(FormulaError, match=r"'\(t1-t1\)' is '\(t1-t1\)': identically zero"):
        compile_formula("(t1-t1)", cols)
    with pytest.raises(FormulaError, match=r"a probe named 'tc'"):
        compile_formula("tc", cols + ["temp_tc"], channel_probe="t1")
    ds = own_probe_run(PROFILE[:2])
    broken = Dataset({k: v for k, v in ds.columns.items() if k != "temp_t2"}, ds.meta)
    with pytest.raises(DataFormatError, match=r"channel 'y': its probe 't2'"):
        fit_model("tc + dtc", broken, "y")
    assert "probe" not in fit_model("t1 + dt1", broken, "y").definition   # a formula without tc still fits


# --------------------------------------------------------------------------------- CLI, import, API
def test_bench_fit_tc_formula_on_csv_files_per_channel(tmp_path):
    write_csv(own_probe_run(seed=6), tmp_path / "train.csv")
    write_csv(own_probe_run(PROFILE_V, seed=7), tmp_path / "val.csv")
    out = tmp_path / "fit.json"
    res = runner.invoke(app, ["fit", "tc + tc^2 + tc^3 + dtc", str(tmp_path / "train.csv"), str(tmp_path / "val.csv"),
                              "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert "y (probe t2): training RMS " in res.output
    doc = json.loads(out.read_text())
    for ch in "xyz":
        entry = doc["channels"][ch]
        assert entry["definition"]["channel_probe"] == OWN[ch]
        assert entry["validation"]["std100_dph"] < 2 * NOISE_STD100


def test_import_keeps_the_map_and_run_dataset_and_export_return_it(tmp_path, monkeypatch):
    from bench.commands.service import import_dataset
    from bench.storage import open_database
    from bench.storage.export import run_dataset
    from bench.storage.models import Run

    db_url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    db = open_database(db_url)
    try:
        ds = own_probe_run(PROFILE[:3], seed=8)
        rid = import_dataset(db, ds, "G-OWN", source="own.csv")
        with db.session() as s:
            assert s.get(Run, rid).config_snapshot["gyro"]["channel_probes"] == OWN
        back = run_dataset(rid, db)
        assert back.meta["channel_probes"] == OWN
        assert fit_model("static", back, "z").definition["probe"] == "t3"
        bad = Dataset(ds.columns, {"channel_probes": {"x": "t1", "y": "t7"}})
        with pytest.raises(DataFormatError, match=r"channel_probes: y=t7 names a probe without a temp_t7 column"):
            import_dataset(db, bad, "G-OWN", source="bad.csv")
    finally:
        db.dispose()
    monkeypatch.setenv("BENCH_DATABASE_URL", db_url)
    res = runner.invoke(app, ["export", str(rid), "--format", "csv", "-o", str(tmp_path / "run.csv")])
    assert res.exit_code == 0, res.output
    assert "# channel_probes: x=t1,y=t2,z=t3\n" in (tmp_path / "run.csv").read_text()
    res = runner.invoke(app, ["fit", "tc + tc^2 + tc^3 + dtc", str(rid), "--json", str(tmp_path / "f.json")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "f.json").read_text())
    assert {ch: e["definition"]["channel_probe"] for ch, e in doc["channels"].items()} == OWN


def test_api_fit_with_tc_formula_shows_the_probe_per_channel(tmp_path):
    from fastapi.testclient import TestClient

    from api.app import create_app
    from bench.commands.service import import_dataset
    from bench.jobs import JobRunner
    from bench.storage import open_database
    from tests.api_support import ADMIN, OPERATOR, TOKENS, VIEWER

    db = open_database(f"sqlite:///{tmp_path / 'api.sqlite'}")
    client = TestClient(create_app(db, tokens=TOKENS))
    try:
        train = import_dataset(db, own_probe_run(seed=9), "G-OWN")
        val = import_dataset(db, own_probe_run(PROFILE_V, seed=10), "G-OWN")
        r = client.post("/fits", json={"model": "tc + tc^2 + tc^3 + dtc", "run_ids": [train],
                                       "validation_run_ids": [val]}, headers=OPERATOR)
        assert r.status_code == 202, r.text
        assert JobRunner(db).run_pending() == [(r.json()["id"], "done")]
        fit_id = client.get(r.json()["url"], headers=VIEWER).json()["result"]["fit_id"]
        fit = client.get(f"/fits/{fit_id}", headers=VIEWER).json()
        assert {ch: e["probe"] for ch, e in fit["channels"].items()} == OWN
        assert fit["channels"]["y"]["definition"]["terms"][1]["expr"] == "t2"
        assert fit["channels"]["y"]["metrics"]["validation"]["std100_dph"] < 2 * NOISE_STD100
        assert client.post(f"/fits/{fit['id']}/accept", headers=ADMIN).status_code == 200
        coeffs = client.get("/gyros/G-OWN/coefficients", headers=VIEWER).json()
        assert {ch: e["probe"] for ch, e in coeffs["models"][0]["channels"].items()} == OWN
        # runs whose maps disagree are refused rather than fitted with the wrong probe
        other = import_dataset(db, own_probe_run(PROFILE[:3], seed=11, mapping={"x": "t1", "y": "t4"}), "G-OWN")
        r = client.post("/fits", json={"model": "static", "run_ids": [train, other]}, headers=OPERATOR)
        assert r.status_code == 202
        JobRunner(db).run_pending()
        job = client.get(r.json()["url"], headers=VIEWER).json()
        assert job["status"] == "failed" and "channel y: probe t4 in run" in job["error"]
    finally:
        client.close()
        db.dispose()


def test_demo_declares_the_channel_probe_model_of_its_scenario():
    from bench.commands.demo import DECLARED

    sc = Scenario.builtin("default")
    assert uses_channel_probe(DECLARED)
    cols = ["time_s"] + [f"temp_{p}" for p in sc.probes]
    names = sc.temperature_names()
    for ch, probe in sc.channel_probe_map().items():
        compiled = compile_formula(DECLARED, cols, channel_probe=probe)
        leaves = {(leaf["op"], leaf["column"]) for leaf in compiled.signal_nodes().values()}
        # every signal a true bias term of the channel is built on is an input of the declared model
        for term in sc.bias[ch].terms:
            for f in parse_term(term, names):
                for name in filter(None, (f.a, f.b)):
                    op = "rate" if f.kind in ("rate", "grad_rate") else "temp"
                    assert (op, f"temp_{name}") in leaves, (ch, term, DECLARED)

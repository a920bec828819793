"""Every procedure, shortened through ``--param``, runs end to end with ``bench run --sim`` (simulated
bench in accelerated time, real drivers on loopback transports) against SQLite and PostgreSQL; the
stored run is then read back with ``bench runs show`` and ``bench export``."""
from __future__ import annotations

import json

import numpy as np
import pytest
from sqlalchemy import select

from bench.fit.csvio import read_csv
from bench.storage.db import open_database
from bench.storage.models import FrameChunk, Segment, Step
from tests.test_runs_support import cli

SPEED = "600"

# name -> (params, expected segment labels check)
SHORT = {
    "eight_position": ["points_c=[20,30]", "soak_h=0.04", "record_min=1"],
    "thermal_ramp": ["start_c=26", "soak_h=0.04", "warmup_min=1", "rate_c_per_min=2", "end_c=22",
                     "final_hold_min=1"],
    "rate_cycle": ["low_c=20", "high_c=30", "initial_soak_h=0.02", "cycle_step_c=10", "cycle_hold_min=1",
                   "rates_c_per_min=[2.0]", "dwell_min=0.5",
                   'validation=[{"target_c":26,"rate_c_per_min":2,"hold_min":1},'
                   '{"target_c":21,"rate_c_per_min":2,"hold_min":1},'
                   '{"target_c":29,"rate_c_per_min":2,"hold_min":1},'
                   '{"target_c":23,"rate_c_per_min":2,"hold_min":1}]'],
    "hrg_calibration": ["points_c=[24,26]", "soak_h=0.03", "record_min=1", "cold_c=22", "cool_expected_h=0.05",
                        "cool_timeout_h=0.3", "cold_soak_h=0.01", "rate_c_per_min=2", "end_c=25",
                        "probe_tol_c=2", "until_timeout_h=0.2"],
    "fog_startup": ["points_c=[24]", "orientations=[\"ENU\",\"WSU\"]", "settle=soak", "soak_h=0.03",
                    "record_min=1"],
}
SCENARIO = {"hrg_calibration": "hrg", "fog_startup": "fog_effects"}


def _run(name: str, url: str) -> dict:
    args = ["run", name, "--gyro", f"G-{name}", "--sim", "--speed", SPEED, "--data-rate", "1", "--json",
            "--no-progress", "--db", url, "--scenario", SCENARIO.get(name, "default")]
    for p in SHORT[name]:
        args += ["--param", p]
    code, out, err = cli(args)
    doc = json.loads(out)                # --json: stdout is exactly one JSON object
    assert f"run {doc['run_id']}\n" in err, err[-2000:]
    assert code == 0 and doc["status"] == "completed", (doc, err[-2000:])
    return doc


def _check_stored(url: str, doc: dict, name: str) -> None:
    rid = doc["run_id"]
    code, out, _ = cli(["runs", "show", str(rid), "--json", "--db", url])
    show = json.loads(out)
    assert code == 0 and show["status"] == "completed" and show["outcome"] == "completed"
    assert show["step"] == show["n_steps"] and show["progress"] == pytest.approx(1.0)
    assert show["frames"] == doc["frames"] > 100
    assert show["gaps"] == [] and show["suspensions"] == []
    db = open_database(url)
    try:
        with db.session() as s:
            steps = list(s.scalars(select(Step).where(Step.run_id == rid).order_by(Step.index)))
            segs = list(s.scalars(select(Segment).where(Segment.run_id == rid)))
            chunks = s.execute(select(FrameChunk.first_index, FrameChunk.count).where(FrameChunk.run_id == rid)
                               .order_by(FrameChunk.first_index)).all()
        assert [st.status for st in steps[:-1]] == ["done"] * (len(steps) - 1)     # the fit may fail on tiny data
        assert steps[-1].kind == "fit" and steps[-1].status in ("done", "failed")
        assert segs and all(sg.t_end > sg.t_start for sg in segs)
        assert all(sg.orientation for sg in segs), [sg.labels for sg in segs if not sg.orientation]
        # frame indexes 0..n-1, each once
        expected = 0
        for first, count in chunks:
            assert first == expected
            expected += count
        assert expected == doc["frames"]
    finally:
        db.dispose()


@pytest.mark.parametrize("name", list(SHORT))
def test_procedure_end_to_end_sqlite(tmp_path, name):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    doc = _run(name, url)
    _check_stored(url, doc, name)
    if name == "thermal_ramp":
        _check_thermal_ramp_and_export(tmp_path, url, doc)
    _check_round_trip(tmp_path, url, doc, name)


# the model fitted in the round trip: the procedure's own where the shortened run has enough data for it
# (the shortened fog_startup records one minute per orientation at one point: too little for its
# stepwise / Delaunay models, so a linear formula in T1 stands in)
ROUND_TRIP_MODEL = {"eight_position": ("static", {}), "thermal_ramp": ("dynamic", {}),
                    "rate_cycle": ("patent37", {}), "hrg_calibration": ("hrg_reverse", {"reference": "t1"}),
                    "fog_startup": ("t1", {})}


def _check_round_trip(tmp_path, url: str, doc: dict, name: str) -> None:
    """export (CSV v1) -> import -> fit gives the fit by run ID; the export carries what a fit needs."""
    from bench.commands.importing import import_csv
    from bench.fit.catalog import fit_model
    from bench.storage.export import run_dataset

    rid = doc["run_id"]
    path = tmp_path / "round.csv"
    code, _, err = cli(["export", str(rid), "--format", "csv", "--recorded-only", "-o", str(path), "--db", url])
    assert code == 0, err
    exported = read_csv(path)
    for key in ("latitude_deg", "gyro_id", "gyro_type", "sample_period_s"):
        assert exported.meta.get(key), (key, exported.meta)
    assert "orientation" in exported and set(exported["orientation"]) - {""}
    db = open_database(url)
    try:
        by_id = run_dataset(rid, db)
        rid2 = import_csv(db, path, f"G-{name}")
        again = run_dataset(rid2, db)
    finally:
        db.dispose()
    model, opts = ROUND_TRIP_MODEL[name]
    channel = "x" if "gyro_x" in by_id or model.startswith("hrg_") else by_id.gyro_channels()[0]
    a = fit_model(model, by_id, channel, **opts)
    for other in (fit_model(model, exported, channel, **opts), fit_model(model, again, channel, **opts)):
        assert other.coefficients.keys() == a.coefficients.keys()
        for term, value in a.coefficients.items():      # gyro values pass through float32 frames once
            assert other.coefficients[term] == pytest.approx(value, rel=1e-5, abs=1e-6 * (1 + abs(value))), term
        assert other.definition.get("earth_rate") == a.definition.get("earth_rate")


def _check_thermal_ramp_and_export(tmp_path, url: str, doc: dict) -> None:
    rid = doc["run_id"]
    db = open_database(url)
    try:
        with db.session() as s:
            segs = list(s.scalars(select(Segment).where(Segment.run_id == rid).order_by(Segment.t_start)))
    finally:
        db.dispose()
    # default: gyro as mounted, table not moved: the orientation comes from the table angles (ENU at 0, 0)
    assert [sg.labels["phase"] for sg in segs] == ["warmup", "ramp", "cold_hold"]
    assert {sg.orientation for sg in segs} == {"ENU"}
    assert all(sg.labels.get("orientation_from") == "table angles" for sg in segs)
    # the dynamic fit ran through the fit hook
    fit = doc["fits"]["7"]
    assert fit["status"] in ("done", "failed") and fit.get("models", ["dynamic"]) == ["dynamic"]
    # CSV v1 export to a file and to stdout reads back with the fitting module's reader
    path = tmp_path / "run.csv"
    code, _, err = cli(["export", str(rid), "--format", "csv", "-o", str(path), "--db", url])
    assert code == 0, err
    ds = read_csv(path)
    assert set(ds.gyro_channels()) == {"x", "y", "z"} and ds.temp_names() == ["t1", "t2", "t3", "t4"]
    assert len(ds) > 100 and np.all(np.diff(ds.time) > 0)
    assert ds.meta["run_id"] == str(rid) and ds.meta["gyro_id"] == "G-thermal_ramp"
    assert ds.meta["channel_probes"] == {"x": "t1", "y": "t2", "z": "t3"}     # the simulated bench's config
    assert np.nanmax(ds["chamber_sp"]) == pytest.approx(26.0) and np.nanmin(ds["chamber_pv"]) < 24.0
    code, out, _ = cli(["export", str(rid), "--format", "csv", "--db", url, "--recorded-only"])
    rec = read_csv("stdout.csv", text=out)
    assert code == 0 and 0 < len(rec) < len(ds) and set(rec["orientation"]) == {"ENU"}
    assert rec.meta["latitude_deg"]
    pq = tmp_path / "run.parquet"
    code, _, err = cli(["export", str(rid), "--format", "parquet", "-o", str(pq), "--db", url])
    import pyarrow.parquet as papq
    table = papq.read_table(pq)
    assert code == 0 and table.num_rows >= len(ds) and "gyro_x" in table.column_names


@pytest.mark.parametrize("name", ["eight_position", "thermal_ramp", "rate_cycle", "hrg_calibration", "fog_startup"])
def test_procedure_end_to_end_postgresql(pg_url, name):
    url = pg_url
    doc = _run(name, url)
    _check_stored(url, doc, name)


def test_runs_list_shows_runs(tmp_path):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    doc = _run("thermal_ramp", url)
    code, out, _ = cli(["runs", "list", "--json", "--db", url])
    rows = json.loads(out)
    assert code == 0 and [r["run_id"] for r in rows] == [doc["run_id"]] and rows[0]["status"] == "completed"
    code, out, _ = cli(["runs", "list", "--db", url])
    assert code == 0 and "thermal_ramp" in out and "completed" in out

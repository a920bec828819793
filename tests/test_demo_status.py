"""``bench demo`` follows its runs through the run list (status and progress of the run it queued, not
another gyro's or another run's), and the runs it queues are valid thermal ramps; it prints coefficients
with their units, and its ``--dir`` never deletes files an earlier demo did not write.  No worker runs here."""
from __future__ import annotations

import pytest
import typer
from fastapi.testclient import TestClient

from api.app import create_app
from typer.testing import CliRunner

from bench.cli import app
from bench.commands.demo import DEMO_FILES, GYRO_ID, TRAIN, VALIDATE, _fresh_directory, _run_summary, coefficient_lines
from bench.engine import Fit
from procedures import thermal_ramp
from bench.storage import open_database
from tests.api_support import OPERATOR, TOKENS, register_bench


@pytest.fixture()
def client(tmp_path):
    db = open_database(f"sqlite:///{tmp_path / 'api.sqlite'}")
    register_bench(db, "sim1")
    with TestClient(create_app(db, tokens=TOKENS), headers=OPERATOR) as c:
        yield c
    db.dispose()


def _queue(client, gyro_id: str, params: dict) -> int:
    r = client.post("/runs", json={"procedure": "thermal_ramp", "gyro_id": gyro_id, "bench": "sim1",
                                   "params": params, "operator": "demo"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def test_status_is_the_queued_runs_own(client):
    train = _queue(client, GYRO_ID, TRAIN)            # the demo's own parameters are accepted as they are
    _queue(client, "OTHER-GYRO", TRAIN)
    held_out = _queue(client, GYRO_ID, VALIDATE)
    for run_id, params in ((train, TRAIN), (held_out, VALIDATE)):
        row = _run_summary(client, run_id)
        assert (row["id"], row["gyro_id"], row["status"], row["progress_percent"]) == (run_id, GYRO_ID, "queued", 0.0)
        assert client.get(f"/runs/{run_id}").json()["parameters"]["final_hold_min"] == params["final_hold_min"]


def test_a_run_missing_from_the_list_is_an_error(client, capsys):
    _queue(client, GYRO_ID, TRAIN)
    with pytest.raises(typer.Exit):
        _run_summary(client, 999)
    assert "run 999 is not in GET /runs?gyro_id=DEMO-RLG-001" in capsys.readouterr().err


def test_coefficients_are_printed_with_their_units():
    doc = {"gyro_id": GYRO_ID, "models": [{"model": "dynamic", "version": 1, "channels": {
        "x": {"coefficients": {"B0": 0.16247, "k": 0.0020843, "q": 0.27231}, "probe": "t1",
              "units": {"B0": "deg/h", "k": "deg/h/C", "q": "deg/h/(C/min)"}}}}]}
    assert coefficient_lines(doc) == ["dynamic / x (probe t1): B0=0.1625 deg/h, k=0.002084 deg/h/C, q=0.2723 deg/h/(C/min)"]


def test_dir_with_other_files_stops_the_demo_before_anything_is_deleted(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("a week of bench notes")
    (work / "close-loop.json").write_text("{}")
    res = CliRunner().invoke(app, ["demo", "--dir", str(work)])
    assert res.exit_code == 2
    assert f"--dir {work}: holds files the demo did not write (notes.txt)" in res.stderr, res.stderr
    assert sorted(p.name for p in work.iterdir()) == ["close-loop.json", "notes.txt"]     # nothing removed


def test_an_earlier_demos_directory_is_emptied(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    for name in DEMO_FILES:
        (out / name).write_text("old")
    _fresh_directory(out)
    assert out.is_dir() and not any(out.iterdir())
    _fresh_directory(tmp_path / "new" / "demo")                  # a new directory is made, parents too
    assert (tmp_path / "new" / "demo").is_dir()


def test_only_the_modelling_run_fits():
    """The held-out run records without a Fit step, so the coefficients served by gyro ID after the demo
    are those of the modelling run (a fit of the held-out run would store a newer accepted version)."""
    def fits(params: dict) -> list[Fit]:
        return [s for s in thermal_ramp.build(thermal_ramp.Params(**params)).steps if isinstance(s, Fit)]

    assert [f.models for f in fits(TRAIN)] == [TRAIN["fit_models"]]
    assert fits(VALIDATE) == []
    assert len(fits({})) == 1                         # the procedure's default still fits

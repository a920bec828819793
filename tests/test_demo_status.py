"""``bench demo`` follows its runs through the run list (status and progress of the run it queued, not
another gyro's or another run's), and the runs it queues are valid thermal ramps.  No worker runs here."""
from __future__ import annotations

import pytest
import typer
from fastapi.testclient import TestClient

from api.app import create_app
from bench.commands.demo import GYRO_ID, TRAIN, VALIDATE, _run_summary
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


def test_only_the_modelling_run_fits():
    """The held-out run records without a Fit step, so the coefficients served by gyro ID after the demo
    are those of the modelling run (a fit of the held-out run would store a newer accepted version)."""
    def fits(params: dict) -> list[Fit]:
        return [s for s in thermal_ramp.build(thermal_ramp.Params(**params)).steps if isinstance(s, Fit)]

    assert [f.models for f in fits(TRAIN)] == [TRAIN["fit_models"]]
    assert fits(VALIDATE) == []
    assert len(fits({})) == 1                         # the procedure's default still fits

"""``GET /fits`` and ``GET /close-loop``: the stored analyses, newest first, filtered by gyro, model and
day; what the dashboard's lists read."""
from __future__ import annotations

import datetime as dt

from fastapi.testclient import TestClient

from api.app import create_app
from bench.commands.service import import_dataset
from bench.jobs import JobRunner
from bench.storage import open_database
from bench.storage.models import Analysis
from tests.api_support import OPERATOR, TOKENS, VIEWER
from tests.synth import TRAIN_PROFILE, make_run


def test_fit_and_analysis_lists_filter_by_gyro_model_and_day(tmp_path):
    db = open_database(f"sqlite:///{tmp_path / 'api.sqlite'}")
    client = TestClient(create_app(db, tokens=TOKENS))
    try:
        runs = {g: import_dataset(db, make_run(TRAIN_PROFILE[:5], {}, seed=i)[0], g) for i, g in enumerate(("GA", "GB"))}
        for gyro, model in (("GA", "static"), ("GA", "static"), ("GA", "t1 + dt1"), ("GB", "static")):
            r = client.post("/fits", json={"model": model, "run_ids": [runs[gyro]], "channels": ["x"]}, headers=OPERATOR)
            assert r.status_code == 202, r.text          # a fit is a job
        assert [status for _, status in JobRunner(db).run_pending()] == ["done"] * 4
        fits = client.get("/fits", headers=VIEWER).json()["fits"]
        assert [(f["gyro_id"], f["model"], f["version"]) for f in fits][:2] == [("GB", "static", 1), ("GA", "formula", 1)]
        assert len(fits) == 4 and fits[0]["channels"]["x"]["train_std100_dph"] > 0
        got = client.get("/fits", params={"gyro_id": "GA", "model": "static"}, headers=VIEWER).json()["fits"]
        assert [f["version"] for f in got] == [2, 1]
        today = dt.datetime.now(dt.timezone.utc).date()
        day = lambda d: {"date_from": d.isoformat(), "date_to": d.isoformat()}   # noqa: E731
        assert len(client.get("/fits", params=day(today), headers=VIEWER).json()["fits"]) == 4
        assert client.get("/fits", params=day(today - dt.timedelta(days=1)), headers=VIEWER).json()["fits"] == []
        assert len(client.get("/fits", params={"limit": 1}, headers=VIEWER).json()["fits"]) == 1
        assert client.get("/fits", params={"date_from": "yesterday"}, headers=VIEWER).status_code == 422

        with db.session() as s:       # stored analyses as the close-loop job leaves them
            s.add(Analysis(kind="close_loop", gyro_id="GA", request={"model": "static", "train_run_id": 1,
                                                                     "validation_run_id": 2}, status="done",
                           result={"channels": {"x": {"verdict": "explained", "effects_added": [{"kind": "rate"}],
                                                      "before": {"validation_std100_dph": 0.04},
                                                      "after": {"validation_std100_dph": 0.011},
                                                      "noise_floor_dph": 0.0107}}}))
            s.add(Analysis(kind="close_loop", gyro_id="GB", request={"model": "dynamic", "train_run_id": 3,
                                                                     "validation_run_id": 4}, status="failed",
                           error="boom"))
        every = client.get("/close-loop", headers=VIEWER).json()["analyses"]
        assert [a["gyro_id"] for a in every] == ["GB", "GA"]
        ga = client.get("/close-loop", params={"gyro_id": "GA"}, headers=VIEWER).json()["analyses"]
        assert len(ga) == 1 and ga[0]["model"] == "static" and "result" not in ga[0]
        assert ga[0]["channels"]["x"] == {"verdict": "explained", "effects_added": ["rate"],
                                          "before_validation_std100_dph": 0.04, "after_validation_std100_dph": 0.011,
                                          "noise_floor_dph": 0.0107}
        dyn = client.get("/close-loop", params={"model": "dynamic"}, headers=VIEWER).json()["analyses"]
        assert [a["error"] for a in dyn] == ["boom"]
        assert client.get("/close-loop", params=day(today + dt.timedelta(days=1)),
                          headers=VIEWER).json()["analyses"] == []
    finally:
        client.close()
        db.dispose()

"""HTTP layer on its own: auth matrix, validation (problem+json), queue / schedule / cancel,
procedures, benches, coefficients and fits on imported data.  No worker runs here."""
from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from api.app import create_app
from api.auth import parse_tokens
from bench.jobs import JobRunner
from bench.storage import open_database, queries
from tests.api_support import ADMIN, OPERATOR, SHORT_RAMP, TOKENS, VIEWER, register_bench


@pytest.fixture()
def env(tmp_path):
    db = open_database(f"sqlite:///{tmp_path / 'api.sqlite'}")
    register_bench(db, "bench1")
    client = TestClient(create_app(db, tokens=TOKENS))
    yield db, client
    client.close()
    db.dispose()


def run_body(**over):
    body = {"procedure": "thermal_ramp", "gyro_id": "G-001", "bench": "bench1", "params": dict(SHORT_RAMP)}
    body.update(over)
    return body


def is_problem(r, status):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    doc = r.json()
    assert doc["status"] == status and doc["title"] and doc["detail"]
    return doc


def test_tokens_parsing():
    assert parse_tokens("viewer:abcdefgh, operator:ijklmnop") == {"abcdefgh": "viewer", "ijklmnop": "operator"}
    with pytest.raises(ValueError, match="role one of"):
        parse_tokens("guest:abcdefgh")
    with pytest.raises(ValueError, match="shorter than 8"):
        parse_tokens("viewer:abc")
    with pytest.raises(ValueError, match="two roles"):
        parse_tokens("viewer:abcdefgh,admin:abcdefgh")


def test_auth_matrix(env):
    _, c = env
    assert c.get("/health").status_code == 200
    assert c.get("/docs").status_code == 200 and c.get("/openapi.json").status_code == 200
    for path in ("/runs", "/procedures", "/benches", "/gyros/G-001/coefficients"):
        doc = is_problem(c.get(path), 401)
        assert "Bearer" in doc["detail"]
    is_problem(c.get("/runs", headers={"Authorization": "Bearer wrong-token"}), 401)
    assert c.get("/runs", headers=VIEWER).status_code == 200
    # viewer cannot start / stop; operator can
    is_problem(c.post("/runs", json=run_body(), headers=VIEWER), 403)
    r = c.post("/runs", json=run_body(), headers=OPERATOR)
    assert r.status_code == 201, r.text
    rid = r.json()["id"]
    for action in ("stop", "abort", "pause", "resume"):
        doc = is_problem(c.post(f"/runs/{rid}/{action}", headers=VIEWER), 403)
        assert "operator role" in doc["detail"]
    assert c.post(f"/runs/{rid}/stop", headers=OPERATOR).status_code == 200     # queued: cancelled
    assert c.post(f"/runs/{rid + 1000}/stop", headers=OPERATOR).status_code == 404
    # admin is above operator
    assert c.post("/runs", json=run_body(), headers=ADMIN).status_code == 201
    # no token configured at all: everything but health answers 401
    bare = TestClient(create_app(env[0], tokens={}))
    assert "none is configured" in is_problem(bare.get("/runs", headers=VIEWER), 401)["detail"]
    assert bare.get("/health").status_code == 200


def test_validation_messages(env):
    _, c = env
    doc = is_problem(c.post("/runs", json=run_body(colour="red"), headers=OPERATOR), 422)
    assert doc["errors"][0]["where"] == "body.colour" and "unknown field" in doc["errors"][0]["problem"]
    doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, "soak_hours": 1}), headers=OPERATOR), 422)
    assert "body.params.soak_hours" in doc["detail"]
    doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, "soak_h": -1}), headers=OPERATOR), 422)
    assert "body.params.soak_h" in doc["detail"] and "greater than 0" in doc["detail"]
    doc = is_problem(c.post("/runs", json=run_body(procedure="nope"), headers=OPERATOR), 422)
    assert "thermal_ramp" in doc["detail"]
    doc = is_problem(c.post("/runs", json=run_body(bench="other"), headers=OPERATOR), 404)
    assert "bench1" in doc["detail"]
    doc = is_problem(c.post("/runs", json=run_body(gyro_id="bad id!"), headers=OPERATOR), 422)
    assert doc["errors"][0]["where"] == "body.gyro_id"
    doc = is_problem(c.post("/runs", json=run_body(start_at="2030-01-01T22:00:00"), headers=OPERATOR), 422)
    assert "time zone" in doc["detail"]
    # a plan the bench refuses (chamber limits) is refused before anything is queued
    doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, "end_c": -90.0}), headers=OPERATOR), 422)
    assert doc["title"] == "Plan refused"
    assert c.get("/runs", headers=VIEWER).json()["total"] == 0
    is_problem(c.get("/runs/abc", headers=VIEWER), 422)
    is_problem(c.get("/runs?limit=0", headers=VIEWER), 422)
    is_problem(c.get("/nowhere", headers=VIEWER), 404)


def test_bad_parameters_are_refused_when_queued(env):
    """Issue drills: absurd durations and ramp rates, a bool for a number, a model name that is a path,
    an id beyond the database's integers: 422 with the parameter named, nothing queued."""
    db, c = env
    for params, where in (({"soak_h": 1e9}, "soak_h"), ({"rate_c_per_min": 1e-12}, "rate_c_per_min"),
                          ({"soak_h": True}, "soak_h"), ({"fit_models": ["../../etc/passwd"]}, "fit_models.0"),
                          ({"fit_models": ["t1^99999"]}, "fit_models.0"),
                          ({"fit_models": ["(" * 3000 + "t1" + ")" * 3000]}, "fit_models.0")):
        doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, **params}), headers=OPERATOR), 422)
        assert doc["errors"][0]["where"] == f"body.params.{where}", doc
    # every parameter within its bounds, but the whole plan longer than 30 days of bench time
    doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, "soak_h": 719.0, "warmup_min": 43000.0}),
                            headers=OPERATOR), 422)
    assert "30 days" in doc["detail"]
    # faster than the chamber can ramp: the bench config's limit
    doc = is_problem(c.post("/runs", json=run_body(params={**SHORT_RAMP, "rate_c_per_min": 50.0}), headers=OPERATOR),
                     422)
    assert "max_ramp_c_per_min" in doc["detail"]
    assert c.get("/runs", headers=VIEWER).json()["total"] == 0
    for path in ("/runs/7251189334503670677504", "/runs/9223372036854775808/events", "/fits/99999999999999999999999",
                 "/close-loop/99999999999999999999999"):
        is_problem(c.get(path, headers=VIEWER), 422)
    is_problem(c.get("/runs/9223372036854775807", headers=VIEWER), 422)
    is_problem(c.get("/runs/9007199254740991", headers=VIEWER), 404)
    for body in ({"model": "t1^99999", "run_ids": [1]}, {"model": "(" * 20 + "t1" + ")" * 20, "run_ids": [1]},
                 {"model": "static", "run_ids": [2**70]}, {"model": "static", "run_ids": [True]},
                 {"model": "static", "run_ids": [1], "latitude_deg": True}):
        doc = is_problem(c.post("/fits", json=body, headers=OPERATOR), 422)
        assert doc["errors"][0]["where"].startswith("body"), doc
        assert any(k in doc["detail"] for k in ("model", "run_ids", "latitude_deg")), doc


def test_queue_schedule_cancel_and_control_requests(env):
    db, c = env
    later = (dt.datetime.now(dt.timezone.utc) + dt.timedelta(hours=8)).isoformat()
    a = c.post("/runs", json=run_body(start_at=later), headers=OPERATOR).json()
    b = c.post("/runs", json=run_body(gyro_id="G-002"), headers=OPERATOR).json()
    assert a["status"] == b["status"] == "queued" and a["start_at"].startswith(later[:16])
    assert a["estimated_total_bench_s"] > 0
    runs = c.get("/runs?status=queued&bench=bench1", headers=VIEWER).json()
    assert [r["id"] for r in runs["runs"]] == [b["id"], a["id"]]
    assert c.get("/runs?gyro_id=G-002", headers=VIEWER).json()["total"] == 1
    # pause of a queued run makes no sense
    assert "queued" in is_problem(c.post(f"/runs/{b['id']}/pause", headers=OPERATOR), 409)["detail"]
    # cancel the scheduled run
    r = c.post(f"/runs/{a['id']}/abort", headers=OPERATOR)
    assert r.status_code == 200 and r.json()["cancelled"]
    detail = c.get(f"/runs/{a['id']}", headers=VIEWER).json()
    assert detail["status"] == "aborted" and "cancelled" in detail["error"]
    is_problem(c.post(f"/runs/{a['id']}/stop", headers=OPERATOR), 409)
    # a running run gets requests written for its worker, in order
    with db.session() as s:
        run = queries.get_run(s, b["id"], for_update=True)
        run.status = "running"
    assert c.post(f"/runs/{b['id']}/pause", headers=OPERATOR).status_code == 202
    assert c.post(f"/runs/{b['id']}/stop", headers=OPERATOR).status_code == 202
    pending = c.get(f"/runs/{b['id']}", headers=VIEWER).json()["pending_requests"]
    assert [p["command"] for p in pending] == ["pause", "stop"]
    from bench.worker import DbControl
    ctl = DbControl(db, b["id"], min_interval_s=0.0)
    assert [ctl.poll(), ctl.poll(), ctl.poll()] == ["pause", "stop", None]
    events = c.get(f"/runs/{b['id']}/events", headers=VIEWER).json()["events"]
    assert [e["kind"] for e in events] == ["queued", "request_pause", "request_stop"]


def test_procedures_and_benches(env):
    _, c = env
    procs = {p["name"]: p for p in c.get("/procedures", headers=VIEWER).json()["procedures"]}
    assert {"thermal_ramp", "eight_position"} <= set(procs)
    ramp = procs["thermal_ramp"]
    assert ramp["defaults"]["end_c"] == -30.0 and "soak_h" in ramp["parameters_schema"]["properties"]
    assert c.get("/procedures/thermal_ramp", headers=VIEWER).json()["name"] == "thermal_ramp"
    is_problem(c.get("/procedures/none", headers=VIEWER), 422)       # the schema lists the procedures
    benches = c.get("/benches", headers=VIEWER).json()["benches"]
    assert benches[0]["name"] == "bench1" and benches[0]["online"] is False and benches[0]["state"] == "offline"
    assert set(benches[0]["devices"]) == {"chamber", "turntable", "gyro", "probes", "psu"}
    is_problem(c.get("/benches/nope", headers=VIEWER), 404)


def synthetic_dataset(n=1800, seed=0, slope=(0.4, -0.2, 0.1)):
    from bench.fit.base import Dataset
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    T = 10 + 30 * (0.5 - 0.5 * np.cos(2 * np.pi * t / n))      # up and down: rate and temperature decorrelated
    cols = {"time_s": t, "temp_t1": T, "temp_t2": T - 0.3}
    for k, ch in zip(slope, "xyz"):
        cols[f"gyro_{ch}"] = 3.0 + k * (T - 25) + rng.normal(0, 0.05, n)
    cols["orientation"] = np.full(n, "NUE")
    return Dataset(cols, {"gyro_type": "RLG"})


def test_import_fit_accept_coefficients(env):
    db, c = env
    from bench.commands.service import import_dataset
    train = import_dataset(db, synthetic_dataset(seed=1), "G-100", source="train.csv")
    val = import_dataset(db, synthetic_dataset(seed=2), "G-100", source="val.csv")
    is_problem(c.get("/gyros/G-100/coefficients", headers=VIEWER), 404)
    is_problem(c.get("/gyros/NOPE/coefficients", headers=VIEWER), 404)
    body = {"model": "static", "run_ids": [train], "validation_run_ids": [val]}
    is_problem(c.post("/fits", json=body, headers=VIEWER), 403)
    is_problem(c.post("/fits", json={**body, "accept": True}, headers=OPERATOR), 403)   # accepting: admin
    r = c.post("/fits", json=body, headers=OPERATOR)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["status"] == "queued" and r.headers["location"] == job["url"] == f"/jobs/{job['id']}"
    assert c.get(job["url"], headers=VIEWER).json()["status"] == "queued"     # the API process fits nothing
    assert JobRunner(db).run_pending() == [(job["id"], "done")]
    job = c.get(job["url"], headers=VIEWER).json()
    assert job["status"] == "done" and job["attempts"] == 1 and job["report_url"] == f"/fits/{job['fit_id']}/report"
    fit = c.get(f"/fits/{job['result']['fit_id']}", headers=VIEWER).json()
    assert fit["gyro_id"] == "G-100" and fit["version"] == 1 and not fit["accepted"]
    assert fit["channels"]["x"]["coefficients"]["A1"] == pytest.approx(0.4, abs=0.01)
    assert fit["channels"]["y"]["coefficients"]["A1"] == pytest.approx(-0.2, abs=0.01)
    assert fit["channels"]["x"]["metrics"]["validation"]["rms_dph"] < 0.1
    assert set(fit["channels"]["x"]["metrics"]["validation"]) >= {
        "validation_std100_dph", "validation_rms_dph", "validation_coverage", "validation_all_std100_dph"}
    # not accepted yet: no coefficients, but the version can be asked for
    is_problem(c.get("/gyros/G-100/coefficients", headers=VIEWER), 404)
    v1 = c.get("/gyros/G-100/coefficients?model=static&version=1", headers=VIEWER).json()
    assert v1["models"][0]["accepted"] is False
    is_problem(c.post(f"/fits/{fit['id']}/accept", headers=OPERATOR), 403)
    assert c.post(f"/fits/{fit['id']}/accept", headers=ADMIN).json()["accepted"] is True
    got = c.get("/gyros/G-100/coefficients", headers=VIEWER)
    coeffs, etag = got.json(), got.headers["etag"]
    assert [m["model"] for m in coeffs["models"]] == ["static"]
    assert coeffs["models"][0]["channels"]["z"]["coefficients"]["A1"] == pytest.approx(0.1, abs=0.01)
    # a client holding this answer is told it is unchanged, without a body
    same = c.get("/gyros/G-100/coefficients", headers={**VIEWER, "If-None-Match": etag})
    assert same.status_code == 304 and same.content == b"" and same.headers["etag"] == etag
    # a second accepted version replaces the first
    r2 = c.post("/fits", json={**body, "run_ids": [train, val], "validation_run_ids": [], "accept": True}, headers=ADMIN)
    assert r2.status_code == 202
    JobRunner(db).run_pending()
    assert c.get(r2.json()["url"], headers=VIEWER).json()["result"]["version"] == 2
    assert c.get("/gyros/G-100/coefficients?model=static", headers=VIEWER).json()["models"][0]["version"] == 2
    changed = c.get("/gyros/G-100/coefficients", headers={**VIEWER, "If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["etag"] != etag
    assert changed.json()["models"][0]["version"] == 2
    listing = c.get("/gyros/G-100/fits", headers=VIEWER).json()["fits"]
    assert [(f["version"], f["accepted"]) for f in listing] == [(2, True), (1, False)]
    assert c.get(f"/fits/{fit['id']}", headers=VIEWER).json()["version"] == 1
    report = c.get(f"/fits/{fit['id']}/report", headers=VIEWER)
    assert report.status_code == 200 and report.text.lstrip().lower().startswith("<!doctype html")
    export = c.get(f"/fits/{fit['id']}/export", headers=VIEWER).json()
    assert export["schema"] == "gyrobench.fit.export" and len(export["models"]) == 3
    is_problem(c.get("/fits/99999", headers=VIEWER), 404)
    is_problem(c.post("/fits", json={**body, "run_ids": [99999]}, headers=OPERATOR), 404)
    is_problem(c.post("/fits", json={**body, "model": "t1 +"}, headers=OPERATOR), 422)
    # what only the data can tell ends the job failed, with the reason
    bad = c.post("/fits", json={**body, "model": "t1 + t9"}, headers=OPERATOR).json()
    JobRunner(db).run_pending()
    bad = c.get(bad["url"], headers=VIEWER).json()
    assert bad["status"] == "failed" and "t9" in bad["error"], bad
    # data of the imported run
    data = c.get(f"/runs/{train}/data?stream=seconds&every=100", headers=VIEWER).json()
    assert data["rows"] == 18 and data["columns"]["gyro_x"][0] == pytest.approx(3 + 0.4 * (10 - 25), abs=0.3)
    csv_text = c.get(f"/runs/{train}/data?stream=probes&format=csv&t_from=0&t_to=9", headers=VIEWER).text
    lines = csv_text.strip().splitlines()
    assert lines[0] == "t,name,serial,celsius,fault" and len(lines) == 1 + 20
    is_problem(c.get(f"/runs/{train}/data?t_from=10&t_to=5", headers=VIEWER), 422)


def test_close_loop_job(env):
    db, c = env
    from bench.commands.service import import_dataset
    # close-loop needs at least 3000 s of training data (30 blocks of 100 s)
    train = import_dataset(db, synthetic_dataset(n=4000, seed=3), "G-200")
    val = import_dataset(db, synthetic_dataset(n=4000, seed=4), "G-200")
    body = {"model": "t1", "train_run_id": train, "validation_run_id": val}
    is_problem(c.post("/close-loop", json={**body, "validation_run_id": train}, headers=OPERATOR), 409)
    r = c.post("/close-loop", json=body, headers=OPERATOR)
    assert r.status_code == 202
    aid = r.json()["id"]
    assert r.headers["location"] == f"/close-loop/{aid}"
    assert c.get(f"/close-loop/{aid}", headers=VIEWER).json()["status"] == "queued"
    is_problem(c.get(f"/close-loop/{aid}/report", headers=VIEWER), 409)
    assert JobRunner(db).run_pending() == [(aid, "done")]
    doc = c.get(f"/close-loop/{aid}", headers=VIEWER).json()
    assert doc["status"] == "done", doc["error"]
    assert set(doc["result"]["channels"]) == {"x", "y", "z"}
    assert doc["report_url"] == f"/close-loop/{aid}/report"
    page = c.get(doc["report_url"], headers=VIEWER)         # stored once by the job, served as it is
    assert page.status_code == 200 and page.text.lstrip().lower().startswith("<!doctype html")
    for part in ("before", "after"):
        assert set(doc["result"]["channels"]["x"][part]) >= {
            "validation_std100_dph", "validation_rms_dph", "validation_coverage", "validation_all_std100_dph"}
    is_problem(c.get("/close-loop/9999", headers=VIEWER), 404)


def test_fit_stored_without_a_job_gets_its_report_rendered_by_a_job(env):
    """A fit stored by a run's Fit step has no report yet: the first request queues one rendering job
    (202 with its URL, the same job on a second request); once a worker rendered it, the page is served."""
    db, c = env
    from bench.commands.service import import_dataset
    from bench.fit.models import fit_model
    from bench.storage.models import Fit

    ds = synthetic_dataset(seed=5)
    train = import_dataset(db, ds, "G-300")
    with db.session() as s:
        queries.save_fits(s, "G-300", [train], [fit_model("static", ds, ch) for ch in "xyz"])
        fit_id = min(s.scalars(select(Fit.id).where(Fit.gyro_id == "G-300")))
    first = c.get(f"/fits/{fit_id}/report", headers=VIEWER)
    assert first.status_code == 202 and first.json()["kind"] == "fit_report"
    again = c.get(f"/fits/{fit_id + 1}/report", headers=VIEWER)        # another channel of the same version
    assert again.status_code == 202 and again.json()["id"] == first.json()["id"]
    assert JobRunner(db).run_pending() == [(first.json()["id"], "done")]
    page = c.get(f"/fits/{fit_id + 2}/report", headers=VIEWER)
    assert page.status_code == 200 and "G-300: static v1" in page.text

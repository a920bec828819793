"""Prometheus metrics: ``GET /metrics`` of the API and a worker's metrics port move when a simulated run
records; writer buffers, gaps and suspensions are counted; JSON-lines logs."""
from __future__ import annotations

import json
import logging
import urllib.request

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from api.app import create_app
from bench.metrics import api_registry, exposition, serve_worker_metrics
from bench.storage import FrameWriter, open_database, queries
from bench.storage.models import Suspension
from tests.api_support import OPERATOR, SHORT_RAMP, TOKENS, VIEWER, DoublesBench, start_worker, unique_bench, wait_for
from tests.service_support import SAFETY_S
from tests.test_storage_support import make_frames


def samples(text: str) -> dict[tuple[str, tuple], float]:
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def value(m: dict, name: str, **labels) -> float:
    return m.get((name, tuple(sorted(labels.items()))), 0.0)


@pytest.fixture()
def db(tmp_path):
    database = open_database(f"sqlite:///{tmp_path / 'm.sqlite'}")
    yield database
    database.dispose()


def test_api_and_worker_metrics_move_when_a_simulated_run_records(db):
    name = unique_bench()
    worker, thread = start_worker(db, name, DoublesBench.lockstep())
    server, _ = serve_worker_metrics(worker, 0)
    c = TestClient(create_app(db, tokens=TOKENS, stale_after_s=1.5))

    def api() -> dict:
        r = c.get("/metrics", headers=VIEWER)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        return samples(r.text)

    def own() -> dict:
        with urllib.request.urlopen(f"http://127.0.0.1:{server.server_port}/metrics", timeout=5) as resp:
            return samples(resp.read().decode())

    try:
        assert c.get("/metrics").status_code == 401
        before = api()
        assert value(before, "bench_frames_stored_total", bench=name) == 0
        assert value(before, "bench_runs", bench=name, status="completed") == 0
        body = {"procedure": "thermal_ramp", "gyro_id": "RLG-M", "bench": name, "start_at": None,
                "params": dict(SHORT_RAMP, soak_h=0.02, final_hold_min=0.5)}
        rid = c.post("/runs", json=body, headers=OPERATOR).json()["id"]
        counted = api()                     # queued, running or already done: counted once whatever its status
        assert sum(v for (n, labels), v in counted.items()
                   if n == "bench_runs" and ("bench", name) in labels) == 1
        mid = wait_for(lambda: (m := api()) and value(m, "bench_frames_stored_total", bench=name) > 0 and m, SAFETY_S,
                       "frames stored while the run records")
        wait_for(lambda: c.get(f"/runs/{rid}", headers=VIEWER).json()["status"] in ("completed", "aborted", "failed"),
                 SAFETY_S, "the run to end")
        wait_for(lambda: worker.current_run is None, SAFETY_S, "the worker to finish the run")
        after = api()
        assert c.get(f"/runs/{rid}", headers=VIEWER).json()["status"] == "completed"
        assert value(after, "bench_runs", bench=name, status="completed") == 1
        assert value(after, "bench_queue_depth", bench=name) == 0
        stored = value(after, "bench_frames_stored_total", bench=name)
        assert stored >= value(mid, "bench_frames_stored_total", bench=name) > 0
        with db.session() as s:
            assert stored == queries.frame_count(s, rid)
        assert value(after, "bench_run_duration_seconds_count", bench=name) == 1
        assert value(after, "bench_run_duration_seconds_sum", bench=name) > 0
        assert value(after, "bench_worker_heartbeat_age_seconds", bench=name) < 10
        w = own()                                   # the worker's own endpoint: its bench, its runs
        assert value(w, "bench_frames_stored_total", bench=name) == stored
        assert value(w, "bench_worker_runs_total", bench=name, status="completed") == 1
        assert value(w, "bench_worker_busy", bench=name) == 0
    finally:
        worker.stop()
        thread.join(timeout=30)
        server.shutdown()
        c.close()


def test_buffered_frames_gaps_and_suspensions_are_counted(db):
    with db.session() as s:
        rid = queries.create_run(s, procedure="test", gyro_id="G-M", bench_name="bm",
                                 config_snapshot={"gyro": {"output_units": "deg/s"}}).id
    reg = api_registry(db)

    def now() -> dict:
        return samples(exposition(reg)[0].decode())

    w = FrameWriter(db, rid, autostart=False)
    w.add_many(make_frames(1500))
    m = now()
    assert value(m, "bench_frames_buffered", run=str(rid)) == 1500
    assert value(m, "bench_frames_stored_total", bench="bm") == 0
    w.record_gap(10.0, 10.5, "link_drop", frames_missing=500)
    w.flush()
    m = now()
    assert value(m, "bench_frames_buffered", run=str(rid)) == 0
    assert value(m, "bench_frames_stored_total", bench="bm") == 1500
    assert value(m, "bench_gaps_total", bench="bm", reason="link") == 1
    assert value(m, "bench_frames_lost_total", bench="bm") == 500
    with db.session() as s:
        s.add(Suspension(run_id=rid, t_from=20.0, t_to=30.0, reason="probe fault"))
        s.add(Suspension(run_id=rid, t_from=40.0, t_to=None, reason="chamber alarm"))
    m = now()
    assert value(m, "bench_suspensions_total", bench="bm") == 2
    assert value(m, "bench_suspended_runs", bench="bm") == 1
    w.close()
    assert ("bench_frames_buffered", (("run", str(rid)),)) not in now()     # closed writers leave


def test_json_lines_log(capsys):
    from bench.logs import configure_logging

    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        assert configure_logging("info", "json") == "json"
        logging.getLogger("bench.test").info("run %s queued", 7, extra={"run_id": 7})
        try:
            raise RuntimeError("boom")
        except RuntimeError:
            logging.getLogger("bench.test").exception("failed")
        lines = [json.loads(x) for x in capsys.readouterr().err.strip().splitlines()]
        assert lines[0]["message"] == "run 7 queued" and lines[0]["run_id"] == 7 and lines[0]["level"] == "INFO"
        assert lines[0]["logger"] == "bench.test" and lines[0]["ts"].endswith("Z")
        assert "RuntimeError: boom" in lines[1]["exc"]
        with pytest.raises(ValueError, match="log format"):
            configure_logging("info", "xml")
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])

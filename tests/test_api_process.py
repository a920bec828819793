"""Process-level resilience: the API and the bench worker run as separate processes.

* Kill the API process (SIGKILL) mid-run: the run goes on; a new API process shows it.
* Kill the worker (SIGKILL) mid-run: the run keeps its status with a stale heartbeat; when a worker for
  that bench returns it takes the run over and resumes it from its checkpoint to the end.

The worker process runs this module (``python -m tests.test_api_process worker ...``) on the device
doubles, with a lockstep clock (``bench.clock.LockstepClock``) whose hold file the test writes: the
run stops at a known bench instant while the test kills processes, so nothing here races the wall
clock; a returning worker resumes from the checkpoint with the outage passing in bench time.
tests/test_api_serve.py runs ``bench serve`` (API + worker + simulated bench in one process).
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.api_support import OPERATOR, SHORT_RAMP, TOKENS_TEXT, VIEWER
from tests.service_support import PY, Services, hold_bench_at

T0 = 1_767_225_600.0          # the bench instant the worker's lockstep clock starts at


def _services(db_url: str, tmp: Path) -> Services:
    return Services(tmp, BENCH_DATABASE_URL=db_url, BENCH_TOKENS=TOKENS_TEXT, BENCH_STALE_AFTER_S="1.5")


def _doubles_worker(services: Services, bench: str, clock: dict) -> subprocess.Popen:
    return services.spawn([PY, "-m", "tests.test_api_process", "worker", bench, json.dumps(clock)], "worker.log")


def _get(base: str, rid: int) -> dict:
    r = httpx.get(f"{base}/runs/{rid}", headers=VIEWER, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def _db_run(db_url: str, rid: int):
    from bench.storage import open_database, queries
    db = open_database(db_url)
    try:
        with db.session() as s:
            run = queries.get_run(s, rid)
            return run.status, run.progress, run.heartbeat_at, run.worker
    finally:
        db.dispose()


def test_kill_api_then_worker_mid_run_sqlite_doubles(tmp_path):
    """SQLite; the worker process drives the device doubles (the engine's own test doubles)."""
    from bench.clock import LockstepClock
    from bench.storage import open_database
    from tests.api_support import register_bench

    db_url = f"sqlite:///{tmp_path / 'proc.sqlite'}"
    db = open_database(db_url)       # migrate once before the processes start
    register_bench(db, "proc1")
    db.dispose()
    hold = tmp_path / "hold"
    clock = LockstepClock(T0, 150.0, hold_file=str(hold)).to_json()
    with _services(db_url, tmp_path) as services:
        _kill_and_resume(services, db_url, lambda: _doubles_worker(services, "proc1", clock), SHORT_RAMP,
                         check_fit=True, hold=hold)


@pytest.mark.postgres
def test_kill_api_then_worker_mid_run_postgres_doubles(pg_fresh_url, tmp_path):
    """The same on PostgreSQL (row locks: the claim and the takeover run under SELECT ... FOR UPDATE)."""
    from bench.clock import LockstepClock
    from bench.storage import open_database
    from tests.api_support import register_bench

    db = open_database(pg_fresh_url)
    register_bench(db, "proc1")
    db.dispose()
    hold = tmp_path / "hold"
    clock = LockstepClock(T0, 150.0, hold_file=str(hold)).to_json()
    with _services(pg_fresh_url, tmp_path) as services:
        _kill_and_resume(services, pg_fresh_url, lambda: _doubles_worker(services, "proc1", clock), SHORT_RAMP,
                         check_fit=True, hold=hold)


def _kill_and_resume(services: Services, db_url: str, start_worker, params: dict, check_fit: bool,
                     hold: Path) -> None:
    hold.write_text(repr(T0 + 200.0))           # about a third into the short ramp run (~700 bench s)
    api, base = services.api()
    worker = start_worker()
    services.wait_for(lambda: httpx.get(f"{base}/benches/proc1", headers=VIEWER, timeout=30).json().get("online"),
                      "worker online", worker, interval=0.1)
    body = {"procedure": "thermal_ramp", "gyro_id": "RLG-P", "bench": "proc1", "params": params}
    r = httpx.post(f"{base}/runs", json=body, headers=OPERATOR, timeout=30)
    assert r.status_code == 201, r.text
    rid = r.json()["id"]
    log = services.log_of(worker)
    hold_bench_at(hold, T0 + 200.0, proc=worker, log=log)
    services.wait_for(lambda: (_db_run(db_url, rid)[1] or 0) > 0.03, "progress published at the hold", worker)
    # 1. the API dies: the run goes on (bench time moves on to a second hold)
    services.kill(api)
    before = _db_run(db_url, rid)[1]
    hold_bench_at(hold, T0 + 350.0, proc=worker, log=log)
    services.wait_for(lambda: _db_run(db_url, rid)[1] > before, "progress after the API died", worker)
    status, after, *_ = _db_run(db_url, rid)
    assert status == "running" and after > before
    _, base = services.api()
    doc = _get(base, rid)
    assert doc["status"] == "running" and doc["worker_alive"]
    # 2. the worker dies (kill -9) while held mid-run: the run is left running with a stale heartbeat
    services.kill(worker)
    stuck = services.wait_for(lambda: (d := _get(base, rid))["worker_alive"] is False and d, "stale heartbeat")
    assert stuck["progress_percent"] < 100
    assert stuck["status"] in ("running", "paused", "suspended")
    frozen = stuck["progress_percent"]
    # a worker for the bench returns (no hold): it takes the run over and resumes it
    hold.unlink()
    worker = start_worker()
    done = services.wait_for(lambda: (d := _get(base, rid))["status"] in ("completed", "failed", "aborted") and d,
                             "resumed run finished", worker)
    assert done["outcome"] == "completed", done
    assert done["progress_percent"] == pytest.approx(100.0) and frozen < 100
    assert any(g["reason"] == "crash_resume" for g in done["gaps"])
    kinds = [e["kind"] for e in httpx.get(f"{base}/runs/{rid}/events", headers=VIEWER, timeout=30).json()["events"]]
    assert "worker_takeover" in kinds and "run_resumed" in kinds
    if check_fit:
        assert done["fits"] and list(done["fits"].values())[-1]["status"] == "done", done["fits"]
        coeffs = httpx.get(f"{base}/gyros/RLG-P/coefficients", headers=VIEWER, timeout=30).json()
        assert coeffs["models"][0]["model"] == "dynamic" and coeffs["models"][0]["run_ids"] == [rid]


def _doubles_worker_main(bench: str, clock_json: str) -> None:
    """Entry of the worker process used above: a Worker on fresh device doubles."""
    import logging

    from bench.clock import clock_from_json
    from bench.storage import open_database
    from bench.worker import Worker
    from tests.api_support import DoublesBench, bench_config, engine_config

    logging.basicConfig(level=logging.INFO)
    doubles = DoublesBench(clock_from_json(json.loads(clock_json)))
    w = Worker(open_database(), bench, bench_config(bench), doubles.factory, doubles.clock,
               engine_config=engine_config(), heartbeat_s=0.2, stale_after_s=1.5, poll_s=0.05)
    signal.signal(signal.SIGTERM, lambda *_: w.stop())
    w.run_forever()


if __name__ == "__main__" and len(sys.argv) == 4 and sys.argv[1] == "worker":
    _doubles_worker_main(sys.argv[2], sys.argv[3])

"""End to end through HTTP with an in-process bench worker on the device doubles, on SQLite and on
PostgreSQL: start a shortened thermal_ramp, watch progress, pause / resume, stop it, start another, let
it finish, fetch the coefficients by gyro ID; scheduling; one run per bench; SSE.

The doubles run on a lockstep clock.  The test reads the run and requests pause / resume while bench
time stands at known instants.  What it reads there was published by the worker (about every
``heartbeat_s`` wall seconds) and requests are taken within ``DbControl.min_interval_s`` wall seconds, so
the clock is paced (at most ``PACE`` bench s per wall s, ``LockstepClock.BURST_WALL_S`` of catching up
at most): two instants ``k * PACE`` bench seconds apart are at least ``k - 0.25`` wall seconds apart
however loaded the host, time for several publishes and request polls.  Load only stretches that."""
from __future__ import annotations

import datetime as dt
import json

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from tests.api_support import (OPERATOR, SHORT_RAMP, T0, TOKENS, VIEWER, DoublesBench, register_bench,
                               start_worker, unique_bench, wait_for)
from tests.service_support import SAFETY_S, hold_clock_at

PACE = 150.0
LAG = 0.45 * PACE + 10.0     # a wall poll interval (0.2 s) + the clock's catching up, + a tick



def run_doc(c, rid):
    r = c.get(f"/runs/{rid}", headers=VIEWER)
    assert r.status_code == 200, r.text
    return r.json()


def test_ramp_progress_pause_stop_then_complete_and_coefficients(db):
    # the run (SHORT_RAMP on the doubles): soak at 30 C to T0+182 s, gyro on, warm-up, ramp from T0+242 s
    # to T0+542 s, cold hold to T0+662 s.  A request is taken within about LAG bench s of the instant
    # the clock goes on from a hold; what is read at a hold was published at most LAG bench s before.
    name = unique_bench()
    doubles = DoublesBench.lockstep(pace=PACE)
    clock = doubles.clock
    clock.hold_at(T0 + 200.0)                  # the soak at 30 C, the gyro on since T0+182 s
    worker, thread = start_worker(db, name, doubles)
    c = TestClient(create_app(db, tokens=TOKENS, stale_after_s=1.5, sse_poll_s=0.05))
    try:
        wait_for(lambda: c.get(f"/benches/{name}", headers=VIEWER).json()["online"], SAFETY_S, "worker online")
        body = {"procedure": "thermal_ramp", "gyro_id": "RLG-7", "bench": name, "params": SHORT_RAMP}
        first = c.post("/runs", json=body, headers=OPERATOR).json()["id"]
        ended = lambda: run_doc(c, first)["status"] in ("completed", "aborted", "failed")  # noqa: E731
        hold_clock_at(clock, T0 + 200.0, ended)
        doc = run_doc(c, first)
        assert doc["progress_percent"] > 5 and doc["status"] == "running" and doc["worker_alive"]
        assert doc["step"]["n_steps"] == 9 and doc["eta_utc"] and doc["remaining_bench_s"] > 0
        bench = c.get(f"/benches/{name}", headers=VIEWER).json()
        assert bench["state"] == "busy" and bench["current_run"]["id"] == first
        # latest readings are there while it runs (stored by the writer's thread while the clock stands)
        latest = wait_for(lambda: (d := run_doc(c, first)["latest"]).get("gyro") and d, SAFETY_S, "gyro readings")
        assert {"chamber", "probes", "psu"} <= set(latest)
        assert latest["probes"]["celsius"]["t1"] == pytest.approx(30.0, abs=3.0)
        # pause: the step clock stops while bench time goes on
        assert c.post(f"/runs/{first}/pause", headers=OPERATOR).status_code == 202
        hold_clock_at(clock, T0 + 200.0 + 1.5 * PACE, ended)     # paused by T0+200+LAG, published since
        doc = run_doc(c, first)
        assert doc["status"] == "paused"
        hold_clock_at(clock, T0 + 200.0 + 2.5 * PACE, ended)     # PACE bench seconds later
        later = run_doc(c, first)
        assert later["status"] == "paused" and later["progress_percent"] == doc["progress_percent"]
        assert later["elapsed_bench_s"] >= doc["elapsed_bench_s"] + PACE - LAG
        # resume; then stop (ends after the current recording, safe state) well before the run's end
        assert c.post(f"/runs/{first}/resume", headers=OPERATOR).status_code == 202
        resumed_by = T0 + 200.0 + 2.5 * PACE + 1.5 * LAG
        hold_clock_at(clock, resumed_by, ended)
        assert run_doc(c, first)["status"] == "running"
        assert c.post(f"/runs/{first}/stop", headers=OPERATOR).status_code == 202
        hold_clock_at(clock, resumed_by + 1.5 * LAG, ended)      # the run ends no earlier than T0+959 s
        assert run_doc(c, first)["status"] == "stopping"
        clock.pace = None                      # nothing more is read at a hold: as fast as the host can
        clock.release()
        done = wait_for(lambda: (d := run_doc(c, first))["status"] in ("completed", "aborted", "failed") and d,
                        SAFETY_S, "stopped")
        assert done["status"] == "completed" and done["outcome"] == "stopped", done
        # the queued second run starts once the bench is free and runs to its end
        second = c.post("/runs", json=body, headers=OPERATOR).json()["id"]
        done = wait_for(lambda: (d := run_doc(c, second))["status"] in ("completed", "aborted", "failed") and d,
                        SAFETY_S, "second run finished")
        assert done["outcome"] == "completed", done
        assert done["progress_percent"] == pytest.approx(100.0)
        assert [s["status"] for s in done["steps"]] == ["done"] * 9
        assert done["fits"]["8"]["status"] == "done"
        coeffs = c.get("/gyros/RLG-7/coefficients", headers=VIEWER).json()
        dyn = {m["model"]: m for m in coeffs["models"]}["dynamic"]
        assert dyn["run_ids"] == [second] and dyn["accepted"]
        assert set(dyn["channels"]) == {"x", "y", "z"} and "B0" in dyn["channels"]["x"]["coefficients"]
        # the doubles' gyro outputs a constant 0.001 deg/s = 3.6 deg/h on x
        assert dyn["channels"]["x"]["coefficients"]["B0"] == pytest.approx(3.6, abs=0.05)
        data = c.get(f"/runs/{second}/data?stream=seconds&every=10", headers=VIEWER).json()
        assert data["rows"] > 10 and "temp_t1" in data["columns"]
        # live events (SSE) of a finished run replay and end
        with c.stream("GET", f"/runs/{second}/events?follow=true", headers=VIEWER) as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            text = "".join(r.iter_text())
        kinds = [line[len("event: "):] for line in text.splitlines() if line.startswith("event: ")]
        assert "run_started" in kinds and "run_ended" in kinds and kinds[-1] == "end"
    finally:
        clock.release()
        worker.stop()
        thread.join(timeout=30)
    assert c.get(f"/benches/{name}", headers=VIEWER).json()["state"] == "offline"


def test_schedule_and_one_run_per_bench(db):
    name = unique_bench()
    register_bench(db, name)
    c = TestClient(create_app(db, tokens=TOKENS))
    short = dict(SHORT_RAMP, soak_h=0.02, warmup_min=0.5, end_c=26.0, final_hold_min=0.5)
    body = {"procedure": "thermal_ramp", "gyro_id": "RLG-8", "bench": name, "params": short}
    soon = (dt.datetime.now(dt.timezone.utc) + dt.timedelta(seconds=2.5)).isoformat()
    scheduled = c.post("/runs", json={**body, "start_at": soon}, headers=OPERATOR).json()["id"]
    a = c.post("/runs", json=body, headers=OPERATOR).json()["id"]
    b = c.post("/runs", json=body, headers=OPERATOR).json()["id"]
    doubles = DoublesBench.lockstep()          # as fast as the host can: runs take no wall time to speak of
    w1, t1 = start_worker(db, name, doubles)
    w2, t2 = start_worker(db, name, doubles)       # a second worker for the same bench must wait its turn
    seen_active = []
    try:
        def finished():
            runs = c.get(f"/runs?bench={name}", headers=VIEWER).json()["runs"]
            seen_active.append(sum(r["status"] in ("running", "paused", "stopping", "suspended") for r in runs))
            return all(r["status"] == "completed" for r in runs) and runs
        runs = wait_for(finished, SAFETY_S, "all three runs", interval=0.02)
    finally:
        w1.stop(); w2.stop()
        t1.join(timeout=30); t2.join(timeout=30)
    assert max(seen_active) == 1
    started = {r["id"]: r["started_at"] for r in runs}
    # the one claim order: a scheduled run once due (start_at <= the claim time, which is its
    # started_at), else queued runs in creation order; so a goes first (nothing was due yet), and the
    # next claim takes the scheduled run exactly when that claim came after its start_at
    first, second, third = sorted(started, key=started.get)
    assert first == a and started[scheduled] >= soon
    assert second == (scheduled if started[second] >= soon else b)
    assert {second, third} == {b, scheduled}
    assert len(w1.runs_done) + len(w2.runs_done) == 3

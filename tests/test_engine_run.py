"""A complete run on the device doubles: steps, data, segments, safe state, fit hook."""
from __future__ import annotations

import pytest

from bench.engine import (Fit, GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak, TableRate,
                          WaitStable)
from bench.errors import BenchError
from tests.test_engine_doubles import Bench


def step_times(run, index):
    hist = run.steps[index]["history"]
    return hist[0][0], hist[-1][0]


def test_full_run_records_labelled_data_and_ends_in_safe_state():
    bench = Bench()
    plan = Plan(name="full", steps=[
        Orient(code="ESD"), SetChamber(setpoint_c=30.0), Soak(duration_s=600.0), GyroPower(on=True),
        Record(duration_s=120.0, labels={"temperature_c": 30, "position": "ESD", "repetition": 1}),
        Ramp(target_c=20.0, rate_c_per_min=1.0, record={"phase": "ramp"}),
        WaitStable(tol_c=1.0, probe_rate_c_per_min=0.2, rate_window_s=120.0, stable_s=120.0, expected_s=600.0),
        Orient(code="USE"), Record(duration_s=60.0, labels={"position": "USE"}),
        TableRate(axis="outer", rate_dps=10.0), Record(duration_s=30.0, labels={"rate": 10}),
        GyroPower(on=False), Fit(models=["static"])])
    assert bench.engine().run("r1", plan) == "completed"
    run = bench.run("r1")
    assert [s["status"] for s in run.steps.values()] == ["done"] * len(plan.steps)
    # frames: indexes assigned by the store, contiguous; frames only while powered
    idx = [i for i, _ in run.frames]
    assert idx == list(range(len(idx))) and len(idx) > 0.9 * 5.0 * (120 + 600 + 60)
    on_t, _ = step_times(run, 3)
    _, off_t = step_times(run, 11)
    assert all(on_t <= f.host_time <= off_t for _, f in run.frames)
    # segments with labels and the exact active durations
    seg = {s["step_index"]: s for s in run.segments}
    assert set(seg) == {4, 5, 8, 10}
    assert seg[4]["labels"] == {"temperature_c": 30, "position": "ESD", "repetition": 1, "piece": 0, "complete": True}
    assert seg[4]["t_to"] - seg[4]["t_from"] == pytest.approx(120.0, abs=1.0)
    assert seg[5]["t_to"] - seg[5]["t_from"] == pytest.approx(600.0, abs=6.0)   # 10 C at 1 C/min
    # the ramp was commanded at its rate; the wait ended once stable
    assert ("ramp_to", (20.0, 1.0)) in [(c[1], c[2]) for c in bench.thermal.calls]
    assert any(e["kind"] == "stable" for e in run.events)
    # telemetry and probes were logged periodically
    # (chamber every 5 s, table / PSU every 10 s, probes every 2 s; plain soaks tick every 10 s, so a
    # due read may wait up to one soak tick)
    tel_t = [t for t, _ in run.telemetry]
    assert max(b - a for a, b in zip(tel_t, tel_t[1:])) <= 5.0 + 10.0
    assert sum(1 for a, b in zip(tel_t, tel_t[1:]) if b - a <= 5.0 + 1e-6) > 0.8 * len(tel_t)
    table_t = [t for t, v in run.telemetry if v["turntable"]]
    assert max(b - a for a, b in zip(table_t, table_t[1:])) <= 10.0 + 10.0
    assert sum(1 for a, b in zip(table_t, table_t[1:]) if b - a <= 10.0 + 1e-6) > 0.8 * len(table_t)
    assert len(table_t) < 0.7 * len(tel_t)          # not read at every chamber read
    last = run.telemetry[-1][1]
    assert last["chamber"].pv_c == pytest.approx(bench.thermal.pv, abs=2.0)
    assert set(next(v["turntable"] for _, v in reversed(run.telemetry) if v["turntable"])) == {1, 2}
    assert any(v["psu"] is not None and v["psu"].on and v["psu"].volts == 28.0 for _, v in run.telemetry)
    assert {s["kind"] for s in run.segments} == {"record", "ramp"}
    probe_t = sorted({t for t, _ in run.probes})
    assert max(b - a for a, b in zip(probe_t, probe_t[1:])) <= 2.0 + 10.0
    assert sum(1 for a, b in zip(probe_t, probe_t[1:]) if b - a <= 2.0 + 1e-6) > 0.6 * len(probe_t)
    assert len([r for t, r in run.probes if t == probe_t[5]]) == 4
    # fit: no hook wired -> stored as pending
    assert run.fits[12]["status"] == "fit pending"
    # safe state: chamber set point 25 C, table stopped and parked, gyro off
    assert bench.thermal.setpoint == 25.0
    assert bench.table.pos == {1: 0.0, 2: 0.0} and bench.table.target == {1: 0.0, 2: 0.0}
    assert not bench.psu.on
    # the run's latest telemetry is the bench as the safe state left it: supply off, table parked
    final = run.telemetry[-1][1]
    assert final["psu"] is not None and not final["psu"].on
    assert all(abs(a.position_deg) < 0.01 and a.rate_dps == 0.0 for a in final["turntable"].values())
    kinds = [e["kind"] for e in run.events]
    assert {"safe_chamber", "safe_table", "safe_power"} <= set(kinds)
    assert run.status == "completed" and run.checkpoint["finished"] == "completed"
    with pytest.raises(BenchError, match="already ended"):
        bench.engine().resume("r1")


def test_fit_hook_result_is_stored_and_a_failing_fit_keeps_the_run():
    bench = Bench()
    calls = []

    def hook(run_id, index, step, store):
        calls.append((run_id, index, step.models))
        return {"coefficients": {"k": 0.1}}

    plan = Plan(name="fit", steps=[GyroPower(on=True), Record(duration_s=20.0, labels={"a": 1}),
                                   Fit(models=["static"])])
    assert bench.engine(fit_hook=hook).run("f1", plan) == "completed"
    assert calls == [("f1", 2, ["static"])]
    assert bench.run("f1").fits[2] == {"coefficients": {"k": 0.1}, "status": "done"}

    def broken(run_id, index, step, store):
        raise ValueError("singular matrix")

    assert bench.engine(fit_hook=broken).run("f2", plan) == "completed"
    run = bench.run("f2")
    assert run.steps[2]["status"] == "failed" and "singular matrix" in run.fits[2]["error"]


def test_wait_stable_timeout_continues_or_aborts():
    bench = Bench()
    never = WaitStable(tol_c=0.01, probe_rate_c_per_min=0.001, stable_s=60.0, timeout_s=300.0)
    assert bench.engine().run("w1", Plan(name="w", steps=[SetChamber(setpoint_c=40.0), never])) == "completed"
    assert any(e["kind"] == "stable_timeout" for e in bench.run("w1").events)
    abort = never.model_copy(update={"on_timeout": "abort"})
    assert bench.engine().run("w2", Plan(name="w", steps=[SetChamber(setpoint_c=40.0), abort])) == "failed"
    assert "not stable within 300 s" in bench.run("w2").status_history[-1][2]


def test_ramp_until_every_probe_reaches_the_target():
    bench = Bench()
    plan = Plan(name="u", steps=[Ramp(target_c=35.0, rate_c_per_min=2.0, until_probes_c=35.0, probe_tol_c=0.25)])
    assert bench.engine().run("u1", plan) == "completed"
    run = bench.run("u1")
    reached = [e for e in run.events if e["kind"] == "probes_reached"]
    assert reached and all(v >= 34.75 for v in reached[0]["data"]["probes"].values())
    start, end = step_times(run, 0)
    assert end - start > 300.0 + 600.0   # 5 min of ramp plus the probes' lag


"""Suspension on device conditions, resumption after clear + settle, the cap, link gaps."""
from __future__ import annotations

import pytest

from bench.engine import GyroPower, Plan, Ramp, Record, SetChamber
from tests.test_engine_doubles import Bench, Scripted

RECORD = Plan(name="s", steps=[GyroPower(on=True), Record(duration_s=600.0, labels={"p": 1})])


def set_attr(obj, name, value):
    return lambda: setattr(obj, name, value)


def test_chamber_alarm_suspends_and_the_run_resumes_after_clear_plus_settle():
    bench = Bench(settle_s=60.0)
    t0 = bench.clock.now()
    control = Scripted(bench.clock, [(200.0, set_attr(bench.thermal, "alarm", 4)),
                                     (400.0, set_attr(bench.thermal, "alarm", 0))])
    assert bench.engine(control).run("a", RECORD) == "completed"
    run = bench.run("a")
    (susp,) = run.suspensions
    assert susp["reason"] == "chamber alarm 4"
    assert susp["t_from"] - t0 == pytest.approx(200.0, abs=5.5)           # seen at the next status read
    assert susp["t_to"] - t0 == pytest.approx(400.0 + 60.0, abs=5.5)      # clear + settle
    statuses = [s for _, s, _ in run.status_history]
    assert statuses == ["running", "suspended", "running", "completed"]
    pieces = [s for s in run.segments if s["step_index"] == 1]
    assert len(pieces) == 2 and pieces[0]["t_to"] == susp["t_from"] and pieces[1]["t_from"] == susp["t_to"]
    assert sum(p["t_to"] - p["t_from"] for p in pieces) == pytest.approx(600.0, abs=2.0)


def test_suspension_cap_aborts_to_safe_state_with_the_reason():
    bench = Bench(settle_s=60.0, suspension_cap_s=300.0)
    control = Scripted(bench.clock, [(100.0, set_attr(bench.thermal, "input_error", 1))])
    assert bench.engine(control).run("c", RECORD) == "aborted"
    run = bench.run("c")
    reason = run.status_history[-1][2]
    assert "over the cap of 300 s" in reason and "chamber input error 1" in reason
    assert run.suspensions[0]["t_to"] - run.suspensions[0]["t_from"] == pytest.approx(300.0, abs=1.5)
    assert not bench.psu.on and bench.thermal.setpoint == 25.0


def test_a_condition_coming_back_while_settling_restarts_the_settle_time():
    bench = Bench(settle_s=100.0)
    t0 = bench.clock.now()
    th = bench.thermal
    control = Scripted(bench.clock, [(100.0, set_attr(th, "alarm", 1)), (200.0, set_attr(th, "alarm", 0)),
                                     (250.0, set_attr(th, "alarm", 1)), (300.0, set_attr(th, "alarm", 0))])
    assert bench.engine(control).run("r", RECORD) == "completed"
    (susp,) = bench.run("r").suspensions
    assert susp["t_to"] - t0 == pytest.approx(400.0, abs=5.5)


@pytest.mark.parametrize("fault, reason", [
    (lambda b: b.probes.lost.add("t2"), "probe t2 lost: CRC NO"),
    (lambda b: setattr(b.link, "silent", True), "gyro frames stopped"),
    (lambda b: setattr(b.link, "down", True), "gyro link down"),
])
def test_probe_lost_frames_stopped_and_link_down_suspend(fault, reason):
    bench = Bench(settle_s=30.0)

    def clear():
        bench.probes.lost.clear()
        bench.link.silent = bench.link.down = False

    control = Scripted(bench.clock, [(100.0, lambda: fault(bench)), (300.0, clear)])
    assert bench.engine(control).run("f", RECORD) == "completed"
    (susp,) = bench.run("f").suspensions
    assert reason in susp["reason"]
    assert 100.0 < susp["t_from"] - bench.run("f").created_t < 125.0


def test_suspension_holds_a_running_ramp():
    bench = Bench(settle_s=30.0)
    plan = Plan(name="r", steps=[SetChamber(setpoint_c=30.0), Ramp(target_c=20.0, rate_c_per_min=1.0)])
    control = Scripted(bench.clock, [(120.0, set_attr(bench.thermal, "alarm", 2)),
                                     (300.0, set_attr(bench.thermal, "alarm", 0))])
    assert bench.engine(control).run("r", plan) == "completed"
    names = [c[1] for c in bench.thermal.calls]
    assert names.index("ramp_to") < names.index("hold") < names.index("resume")
    assert [e["kind"] for e in bench.run("r").events].count("ramp_held") == 1


def test_link_gaps_reported_by_the_link_are_stored_as_gaps():
    bench = Bench()
    t0 = bench.clock.now()
    control = Scripted(bench.clock, [(50.0, lambda: bench.link.stats.link_gaps.append((t0 + 40.0, t0 + 45.0)))])
    assert bench.engine(control).run("g", RECORD) == "completed"
    assert {"t_from": t0 + 40.0, "t_to": t0 + 45.0, "reason": "gyro link gap"} in bench.run("g").gaps

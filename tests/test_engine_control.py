"""stop / abort / pause / resume semantics."""
from __future__ import annotations

import pytest

from bench.engine import GyroPower, Plan, QueueControl, Ramp, Record, SetChamber, Soak
from tests.test_engine_doubles import Bench, Scripted


def steps_status(run):
    return {i: s["status"] for i, s in run.steps.items()}


PLAN = Plan(name="ctl", steps=[SetChamber(setpoint_c=30.0), Soak(duration_s=600.0), GyroPower(on=True),
                               Record(duration_s=300.0, labels={"p": 1}), Soak(duration_s=600.0)])


def test_stop_during_a_record_finishes_it_then_goes_safe():
    bench = Bench()
    t0 = bench.clock.now()
    assert bench.engine(Scripted(bench.clock, [(700.0, "stop")])).run("s", PLAN) == "stopped"
    run = bench.run("s")
    seg = run.segments[0]
    assert seg["labels"]["complete"] is True and seg["t_to"] - seg["t_from"] == pytest.approx(300.0, abs=1.0)
    assert steps_status(run) == {0: "done", 1: "done", 2: "done", 3: "done"}   # step 4 never started
    assert [s for _, s, _ in run.status_history] == ["running", "stopping", "stopped"]
    assert bench.thermal.setpoint == 25.0 and not bench.psu.on
    assert seg["t_to"] - t0 == pytest.approx(900.0, abs=1.0)


def test_stop_outside_a_record_stops_at_once():
    bench = Bench()
    t0 = bench.clock.now()
    assert bench.engine(Scripted(bench.clock, [(200.0, "stop")])).run("s", PLAN) == "stopped"
    run = bench.run("s")
    assert steps_status(run) == {0: "done", 1: "stopped"}
    assert run.status_history[-1][0] - t0 < 260.0
    # the run's last progress keeps the 200 s of its 600-s soak it did (of 1500 s planned), not 0 %
    assert run.checkpoint["progress"]["percent"] == pytest.approx(100.0 * 200.0 / 1500.0, abs=0.5)


def test_abort_goes_to_safe_state_now():
    bench = Bench()
    t0 = bench.clock.now()
    assert bench.engine(Scripted(bench.clock, [(750.0, "abort")])).run("a", PLAN) == "aborted"
    run = bench.run("a")
    assert steps_status(run)[3] == "aborted"
    seg = run.segments[0]
    assert seg["labels"]["complete"] is False and seg["t_to"] - t0 == pytest.approx(750.0, abs=1.5)
    kinds = [e["kind"] for e in run.events]
    assert kinds.index("control_abort") < kinds.index("safe_chamber") < kinds.index("safe_power")
    assert run.status_history[-1][2] == "abort requested"
    assert not bench.psu.on and bench.thermal.setpoint == 25.0


def test_pause_stops_the_step_clock_and_resume_continues():
    bench = Bench()
    t0 = bench.clock.now()
    plan = Plan(name="p", steps=[GyroPower(on=True), Record(duration_s=600.0, labels={"p": 1})])
    control = Scripted(bench.clock, [(100.0, "pause"), (400.0, "resume")])
    assert bench.engine(control).run("p", plan) == "completed"
    run = bench.run("p")
    statuses = [s for _, s, _ in run.status_history]
    assert statuses == ["running", "paused", "running", "completed"]
    pieces = [s for s in run.segments if s["step_index"] == 1]
    assert len(pieces) == 2
    assert sum(p["t_to"] - p["t_from"] for p in pieces) == pytest.approx(600.0, abs=2.0)
    assert run.steps[1]["history"][-1][0] - t0 == pytest.approx(900.0, abs=2.0)


def test_pause_holds_a_ramp_and_resume_releases_it():
    bench = Bench()
    plan = Plan(name="p", steps=[SetChamber(setpoint_c=30.0), Ramp(target_c=20.0, rate_c_per_min=1.0)])
    control = Scripted(bench.clock, [(120.0, "pause"), (420.0, "resume")])
    assert bench.engine(control).run("r", plan) == "completed"
    names = [c[1] for c in bench.thermal.calls]
    assert names.index("ramp_to") < names.index("hold") < names.index("resume")
    run = bench.run("r")
    start, end = run.steps[1]["history"][0][0], run.steps[1]["history"][-1][0]
    assert end - start == pytest.approx(600.0 + 300.0, abs=8.0)


def test_stop_while_paused_in_a_record_ends_now_and_queue_control_rejects_unknown():
    bench = Bench()
    control = QueueControl()
    plan = Plan(name="p", steps=[GyroPower(on=True), Record(duration_s=600.0, labels={"p": 1})])
    script = Scripted(bench.clock, [(100.0, lambda: control.request("pause")), (200.0, lambda: control.request("stop"))])

    class Both:
        def poll(self):
            return script.poll() or control.poll()

    assert bench.engine(Both()).run("q", plan) == "stopped"
    assert bench.run("q").segments[0]["labels"]["complete"] is False
    with pytest.raises(ValueError, match="unknown control request 'halt'"):
        control.request("halt")

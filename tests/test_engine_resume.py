"""Checkpoint + resume after a kill -9: the interrupted step continues with its remaining time,
hardware state is restored, the interruption is a gap, and no frame index is duplicated."""
from __future__ import annotations

import pytest

from bench.engine import GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak
from tests.test_engine_doubles import Bench, Killed, Scripted, kill_at


def crash(bench, run_id, plan, at_s):
    engine = bench.engine(control=Scripted(bench.clock, [(at_s, kill_at(at_s))]))
    with pytest.raises(Killed):
        engine.run(run_id, plan)
    return bench.run(run_id).checkpoint


def step_span(run, index):
    hist = [h for h in run.steps[index]["history"]]
    running = [h[0] for h in hist if h[1] == "running"]
    done = [h[0] for h in hist if h[1] == "done"]
    return running, done


def test_soak_continues_with_its_remaining_time():
    bench = Bench(checkpoint_period_s=60.0)
    plan = Plan(name="soak", steps=[SetChamber(setpoint_c=30.0), Soak(duration_s=3600.0),
                                    GyroPower(on=True), Record(duration_s=60.0, labels={"a": 1})])
    cp = crash(bench, "s", plan, 1830.0)
    assert cp["step_index"] == 1 and cp["finished"] is None
    done_before = cp["step_state"]["elapsed_s"]
    assert 1760.0 <= done_before <= 1830.0
    bench.chamber.set_setpoint(0.0)          # someone fiddled with the chamber while we were down
    bench.clock.advance(900.0)               # 15 min outage
    t_resume = bench.clock.now()
    assert bench.engine().resume("s") == "completed"
    run = bench.run("s")
    running, done = step_span(run, 1)
    assert done[0] - t_resume == pytest.approx(3600.0 - done_before, abs=10.0)
    assert ("set_setpoint", (30.0,)) in [(c[1], c[2]) for c in bench.thermal.calls if c[0] >= t_resume]
    assert run.gaps[-1]["t_to"] == t_resume and run.gaps[-1]["t_from"] == pytest.approx(cp["t"])
    assert run.gaps[-1]["reason"] == "engine interrupted"
    assert any(e["kind"] == "run_resumed" for e in run.events)


def test_record_continues_for_the_remaining_time_without_duplicate_frames():
    bench = Bench(checkpoint_period_s=60.0)
    plan = Plan(name="rec", steps=[Orient(code="ESD"), GyroPower(on=True),
                                   Record(duration_s=600.0, labels={"position": "ESD"}), GyroPower(on=False)])
    cp = crash(bench, "r", plan, 330.0)
    assert cp["step_index"] == 2
    elapsed = cp["step_state"]["elapsed_s"]
    frames_before = len(bench.run("r").frames)
    # power cut and the table knocked off position while the engine was dead
    bench.psu.output(False)
    bench.table.move_to(1, 45.0)
    bench.clock.advance(300.0)
    t_resume = bench.clock.now()
    assert bench.engine().resume("r") == "completed"
    run = bench.run("r")
    # hardware restored before continuing
    assert any(e["kind"] == "restore_power" and "on" in e["message"] for e in run.events)
    assert any(f.host_time > t_resume for _, f in run.frames)
    assert any(e["kind"] == "restore_table" and "ESD" in e["message"] for e in run.events)
    # the record's two pieces add up to the planned 600 s
    pieces = sorted((s for s in run.segments if s["step_index"] == 2), key=lambda s: s["labels"]["piece"])
    assert len(pieces) == 2 and all(p["labels"]["position"] == "ESD" for p in pieces)
    assert pieces[0]["t_to"] == pytest.approx(cp["t"])
    assert pieces[1]["t_from"] >= t_resume
    assert sum(p["t_to"] - p["t_from"] for p in pieces) == pytest.approx(600.0, abs=2.0)
    assert pieces[0]["t_to"] - pieces[0]["t_from"] == pytest.approx(elapsed, abs=1.0)
    # frames: store-assigned indexes stay unique and contiguous; no frame stored twice
    idx = [i for i, _ in run.frames]
    assert idx == list(range(len(idx))) and len(idx) > frames_before
    times = [f.host_time for _, f in run.frames]
    assert all(b > a for a, b in zip(times, times[1:]))
    gap = run.gaps[-1]
    assert gap["t_from"] == pytest.approx(max(cp["t"], times[frames_before - 1])) and gap["t_to"] == t_resume
    assert not any(gap["t_from"] < t < gap["t_to"] for t in times)


def test_ramp_is_reissued_from_the_current_temperature():
    bench = Bench(checkpoint_period_s=60.0)
    plan = Plan(name="ramp", steps=[SetChamber(setpoint_c=30.0), Soak(duration_s=1800.0),
                                    Ramp(target_c=10.0, rate_c_per_min=1.0)])
    crash(bench, "m", plan, 1800.0 + 300.0)
    bench.clock.advance(120.0)
    pv = bench.chamber.read_temperature()
    t_resume = bench.clock.now()
    assert bench.engine().resume("m") == "completed"
    run = bench.run("m")
    calls = [(c[1], c[2]) for c in bench.thermal.calls if c[0] >= t_resume]
    assert calls[0] == ("set_power", (True,))
    assert ("set_setpoint", (pv,)) in calls and ("ramp_to", (10.0, 1.0)) in calls
    assert calls.index(("set_setpoint", (pv,))) < calls.index(("ramp_to", (10.0, 1.0)))
    running, done = step_span(run, 2)
    assert pv > 20.0   # the ramp was far from done
    assert done[-1] - t_resume == pytest.approx(abs(pv - 10.0) * 60.0, abs=15.0)
    assert any(e["kind"] == "ramp_reissued" for e in run.events)

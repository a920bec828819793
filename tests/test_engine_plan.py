"""Plan validation refusals, plan summary / durations, progress and ETA."""
from __future__ import annotations

import pytest

from bench.config import BenchConfig, ChamberConfig, TurntableConfig, TurntableGeometry
from bench.engine import (Fit, GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak, TableRate,
                          WaitStable, WeakCorrelation, plan_summary, validate_plan)
from bench.errors import PlanError
from tests.test_engine_doubles import Bench, Scripted


def _plan(*steps):
    return Plan(name="t", steps=list(steps))


@pytest.mark.parametrize("step, words", [
    (SetChamber(setpoint_c=75.0), ["step 1", "75", "-45..70"]),          # above the gyro's max
    (SetChamber(setpoint_c=-60.0), ["step 1", "-60"]),                   # below the gyro's min
    (Ramp(target_c=20.0, rate_c_per_min=6.0), ["step 1", "6 C/min", "maximum 5"]),
    (Ramp(target_c=90.0, rate_c_per_min=1.0), ["step 1", "ramp target 90"]),
    (Ramp(target_c=20.0, rate_c_per_min=0.0), ["step 1", "rate"]),
    (Orient(code="DNS"), ["step 1", "DNS", "right-handed"]),             # the paper's misprint
    (Orient(code="EXU"), ["step 1", "EXU"]),
    (TableRate(axis="outer", rate_dps=150.0), ["step 1", "150", "rate limit 100"]),
    (Record(duration_s=60.0, labels={}), ["step 1", "labels"]),
    (Record(duration_s=0.0, labels={"a": 1}), ["step 1", "duration"]),
    (WaitStable(stable_s=600.0, timeout_s=300.0), ["step 1", "timeout_s"]),
    (Fit(models=[]), ["step 1", "model"]),
])
def test_bad_steps_are_refused_naming_step_and_value(step, words):
    bench = Bench()
    with pytest.raises(PlanError) as err:
        validate_plan(_plan(Soak(duration_s=10.0), step), bench.config)
    for word in words:
        assert word in str(err.value)


def test_chamber_limits_from_config_are_enforced():
    config = BenchConfig(chamber=ChamberConfig(setpoint_min_c=-20.0, setpoint_max_c=50.0))
    with pytest.raises(PlanError, match="set point -30 C is outside the allowed range -20..50"):
        validate_plan(_plan(SetChamber(setpoint_c=-30.0)), config)
    validate_plan(_plan(SetChamber(setpoint_c=-20.0)), config)


def test_unreachable_orientation_for_the_configured_table_is_refused():
    # gyro x on the inner axis (inner axis East, mounting ENU): y can never point up
    x_inner = BenchConfig(turntable=TurntableConfig(geometry=TurntableGeometry(inner_axis=(1.0, 0.0, 0.0))))
    with pytest.raises(PlanError, match="step 0 .*cannot reach USE"):
        validate_plan(_plan(Orient(code="USE")), x_inner)
    validate_plan(_plan(Orient(code="ESD")), x_inner)


def test_empty_plan_and_correlated_parts_are_refused():
    with pytest.raises(PlanError, match="no steps"):
        validate_plan(_plan(), BenchConfig())
    same = [SetChamber(setpoint_c=10.0), Ramp(target_c=40.0, rate_c_per_min=1.0), Ramp(target_c=10.0, rate_c_per_min=1.0)]
    steps = [s.model_copy(update={"part": "model"}) for s in same]
    steps += [s.model_copy(update={"part": "validation"}) for s in same]
    plan = Plan(name="c", steps=steps, constraints=[WeakCorrelation(part_a="model", part_b="validation")])
    with pytest.raises(PlanError, match=r"r = 1\.000"):
        validate_plan(plan, BenchConfig())


def test_a_refused_plan_touches_no_hardware_and_stores_nothing():
    bench = Bench()
    engine = bench.engine()
    with pytest.raises(PlanError):
        engine.run("bad", _plan(SetChamber(setpoint_c=30.0), Ramp(target_c=20.0, rate_c_per_min=9.0)))
    assert bench.thermal.calls == [] and bench.table.calls == [] and bench.psu.calls == []
    assert bench.link.started == 0 and bench.store.runs == {}


def test_summary_durations_add_up():
    bench = Bench()
    plan = Plan(name="s", start_c=25.0, steps=[
        SetChamber(setpoint_c=30.0), Ramp(target_c=40.0, rate_c_per_min=2.0), Soak(duration_s=600.0),
        GyroPower(on=True), Record(duration_s=60.0, labels={"p": 1}),
        WaitStable(expected_s=900.0), Fit(models=["static"])])
    s = plan_summary(plan, bench.config)
    est = [row["est_s"] for row in s["steps"]]
    assert est == [0.0, 300.0, 600.0, 0.0, 60.0, 900.0, 0.0]
    assert s["total_bench_s"] == pytest.approx(1860.0)
    assert s["steps"][4]["start_offset_s"] == pytest.approx(900.0)
    assert s["recorded_bench_s"] == pytest.approx(60.0)
    assert s["setpoint_range_c"] == [30.0, 40.0]


def test_table_move_estimate_uses_angles_and_rate_limit():
    bench = Bench()
    s = plan_summary(_plan(Orient(code="ENU"), Orient(code="WSU")), bench.config)
    tt = bench.config.turntable
    # ENU -> WSU is a 180 deg turn of the outer axis
    assert s["steps"][1]["est_s"] == pytest.approx(180.0 / tt.rate_limit_dps + tt.rate_limit_dps / tt.acceleration_dps2
                                                   + 2.0)


def test_progress_and_eta_during_a_run():
    bench = Bench()
    seen = {}
    engine = bench.engine()

    def sample(key):
        return lambda: seen.__setitem__(key, engine.progress())

    engine.control = Scripted(bench.clock, [(500.0, sample("a")), (1500.0, sample("b"))])
    t0 = bench.clock.now()
    plan = _plan(Soak(duration_s=1000.0), Soak(duration_s=1000.0))
    assert engine.run("p", plan) == "completed"
    a, b = seen["a"], seen["b"]
    assert a["step_index"] == 0 and a["percent"] == pytest.approx(25.0, abs=0.6)
    assert a["remaining_bench_s"] == pytest.approx(1500.0, abs=11.0)
    assert a["eta_bench_t"] == pytest.approx(t0 + 2000.0, abs=11.0)
    assert b["step_index"] == 1 and b["percent"] == pytest.approx(75.0, abs=0.6)
    assert b["eta_bench_t"] == pytest.approx(t0 + 2000.0, abs=11.0)
    cp = bench.run("p").checkpoint
    assert cp["finished"] == "completed" and cp["progress"]["percent"] == pytest.approx(100.0)

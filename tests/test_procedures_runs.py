"""Every procedure, shortened through its parameters, runs to completion on the device doubles."""
from __future__ import annotations

import pytest

from bench.errors import PlanError
from procedures import eight_position, fog_startup, hrg_calibration, rate_cycle, thermal_ramp
from procedures.common import StableParams
from tests.test_engine_doubles import Bench


def run(bench, plan, run_id="r"):
    status = bench.engine().run(run_id, plan)
    stored = bench.run(run_id)
    assert status == "completed", stored.status_history[-1]
    assert all(s["status"] == "done" for s in stored.steps.values())
    assert list(stored.fits.values())[-1]["status"] == "fit pending"
    return stored


def test_eight_position_short():
    bench = Bench()
    plan = eight_position.build(eight_position.Params(points_c=[20.0, 30.0], soak_h=0.05, record_min=0.25))
    stored = run(bench, plan)
    segs = stored.segments
    assert len(segs) == 16
    assert [s["labels"]["position"] for s in segs[:8]] == eight_position.EIGHT_POSITIONS
    assert {s["labels"]["temperature_c"] for s in segs} == {20.0, 30.0}
    assert all(s["t_to"] - s["t_from"] == pytest.approx(15.0, abs=1.0) for s in segs)


def test_thermal_ramp_short():
    bench = Bench()
    plan = thermal_ramp.build(thermal_ramp.Params(orientation="WSU", start_c=30.0, soak_h=0.05, warmup_min=1.0,
                                                  rate_c_per_min=2.0, end_c=20.0, final_hold_min=2.0))
    stored = run(bench, plan)
    phases = [s["labels"]["phase"] for s in stored.segments]
    assert phases == ["warmup", "ramp", "cold_hold"]
    ramp = stored.segments[1]
    assert ramp["t_to"] - ramp["t_from"] == pytest.approx(300.0, abs=6.0)
    assert bench.table.pos[1] != 0.0 or any(c[1] == "move_to" for c in bench.table.calls)


def test_rate_cycle_short_with_enforced_validation():
    bench = Bench(start_c=20.0)
    legs = [rate_cycle.Leg(target_c=a, rate_c_per_min=b, hold_min=c)
            for a, b, c in ((26.0, 1.0, 3.0), (21.0, 2.0, 3.0), (29.0, 2.0, 3.0), (23.0, 1.0, 3.0))]
    params = rate_cycle.Params(low_c=20.0, high_c=30.0, initial_soak_h=0.02, cycle_step_c=10.0, cycle_hold_min=2.0,
                               rates_c_per_min=[2.0, 1.0], dwell_min=1.0, validation=legs)
    assert abs(rate_cycle.correlation(params)) < 0.4
    stored = run(bench, rate_cycle.build(params))
    sets = {s["labels"]["set"] for s in stored.segments}
    assert sets == {"model", "validation"}
    assert {s["labels"]["part"] for s in stored.segments} == {"model", "validation"}
    rates = {s["labels"].get("rate_c_per_min") for s in stored.segments if s["labels"]["phase"] == "rate_cycle"}
    assert rates == {2.0, 1.0}
    # the correlated variant is refused before anything runs
    mirror = [rate_cycle.Leg(target_c=t, rate_c_per_min=r, hold_min=1.0)
              for t, r in ((30.0, 2.0), (20.0, 2.0), (30.0, 1.0), (20.0, 1.0))]   # repeats the rate cycles
    bad = params.model_copy(update={"validation": mirror, "cycle_hold_min": 0.01, "initial_soak_h": 0.0001})
    with pytest.raises(PlanError, match="r = 1.000"):
        rate_cycle.build(bad)


def test_hrg_calibration_short():
    bench = Bench()
    plan = hrg_calibration.build(hrg_calibration.Params(
        points_c=[20.0, 30.0], soak_h=0.05, record_min=1.0, cold_c=15.0, cool_expected_h=0.1, cold_soak_h=0.02,
        rate_c_per_min=2.0, end_c=30.0, probe_tol_c=1.0, until_timeout_h=1.0))
    stored = run(bench, plan)
    labels = [s["labels"] for s in stored.segments]
    assert [l["temperature_c"] for l in labels if l["set"] == "frequency_temperature"] == [20.0, 30.0]
    assert [l["phase"] for l in labels if l["set"] == "dynamic"] == ["cool", "cold_soak", "ramp"]
    assert any(e["kind"] == "probes_reached" for e in stored.events)


def test_fog_startup_short():
    bench = Bench()
    stable = StableParams(tol_c=1.0, probe_rate_c_per_min=0.2, probe_tol_c=1.0, rate_window_min=2.0,
                          stable_min=2.0, timeout_h=1.0, expected_h=0.2)
    plan = fog_startup.build(fog_startup.Params(points_c=[20.0, 30.0], orientations=["ENU", "WSU"], stable=stable,
                                                record_min=2.0))
    stored = run(bench, plan)
    labels = [s["labels"] for s in stored.segments]
    assert [(l["set"], l["position"], l["temperature_c"]) for l in labels] == [
        ("model", "ENU", 20.0), ("model", "ENU", 30.0), ("validation", "WSU", 20.0), ("validation", "WSU", 30.0)]
    assert sum(e["kind"] == "stable" for e in stored.events) == 4
    # frames only while powered: nothing recorded during the unpowered soaks
    powered = [(s["t_from"], s["t_to"]) for s in stored.segments]
    assert all(any(a - 1.0 <= f.host_time <= b + 1.0 for a, b in powered) for _, f in stored.frames)

"""Each procedure's defaults follow its seed paper, and bad parameters are refused."""
from __future__ import annotations

import pytest

import procedures
from bench.config import BenchConfig, TurntableConfig, TurntableGeometry
from bench.devices.orientation import EIGHT_POSITION_GEOMETRY
from bench.engine import (Fit, GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak, WaitStable,
                          plan_summary, validate_plan)
from bench.errors import PlanError
from procedures import eight_position, fog_startup, hrg_calibration, rate_cycle, thermal_ramp

CFG8 = BenchConfig(turntable=TurntableConfig(geometry=EIGHT_POSITION_GEOMETRY))
# gyro x on the inner (tilt) axis: reaches NUE (S000 3.3) but not the eight positions
CFG_X = BenchConfig(turntable=TurntableConfig(geometry=TurntableGeometry(inner_axis=(1.0, 0.0, 0.0))))


def kinds(plan, kind):
    return [s for s in plan.steps if isinstance(s, kind)]


def test_registry_lists_all_five_with_schema():
    mods = procedures.all_procedures()
    assert list(mods) == ["eight_position", "thermal_ramp", "rate_cycle", "hrg_calibration", "fog_startup"]
    for name, mod in mods.items():
        assert mod.NAME == name and mod.DESCRIPTION
        assert "properties" in mod.Params.model_json_schema()
        plan = mod.build(mod.Params())
        assert isinstance(plan, Plan) and isinstance(plan.steps[-1], Fit)
        assert Plan.from_json(plan.to_json()) == plan
    with pytest.raises(KeyError, match="unknown procedure"):
        procedures.get("nine_position")


def test_eight_position_defaults_match_s000_3_2():
    plan = eight_position.build()
    summary = plan_summary(plan, CFG8)
    assert [s.setpoint_c for s in kinds(plan, SetChamber)] == [-40, -30, -20, -10, 0, 10, 20, 30, 40, 50, 60]
    assert {s.duration_s for s in kinds(plan, Soak)} == {4 * 3600.0}
    records = kinds(plan, Record)
    assert len(records) == 11 * 8 and {r.duration_s for r in records} == {60.0}
    assert [r.labels["position"] for r in records[:8]] == ["ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE"]
    assert records[8].labels == {"temperature_c": -30.0, "position": "ESD",
                                                                           "repetition": 1}
    assert 45.5 <= summary["total_bench_h"] <= 46.5          # "about 46 h"
    two = plan_summary(eight_position.build(eight_position.Params(repetitions=2)), CFG8)
    assert two["total_bench_h"] - summary["total_bench_h"] == pytest.approx(11 * 8 / 60.0, abs=0.3)
    # the paper's misprinted eighth position is refused, and the default table geometry cannot do USE
    with pytest.raises(PlanError, match="DNS"):
        validate_plan(eight_position.build(eight_position.Params(positions=["ESD", "DNS"])), CFG8)
    with pytest.raises(PlanError, match="cannot reach USE"):
        validate_plan(plan, CFG_X)


def test_thermal_ramp_defaults_match_s000_3_3():
    plan = thermal_ramp.build()
    assert not kinds(plan, Orient)                 # default: the gyro stays as mounted (S000 mounts it NUE)
    validate_plan(plan, CFG8)
    nue = thermal_ramp.build(thermal_ramp.Params(orientation="NUE"))
    validate_plan(nue, CFG_X)
    with pytest.raises(PlanError, match="cannot reach NUE"):
        validate_plan(nue, CFG8)
    assert nue.steps[0] == Orient(code="NUE")
    assert kinds(plan, SetChamber)[0].setpoint_c == 40.0
    (ramp,) = kinds(plan, Ramp)
    assert (ramp.target_c, ramp.rate_c_per_min, ramp.record["phase"]) == (-30.0, 1.0, "ramp")
    soaks = kinds(plan, Soak)
    assert [s.duration_s for s in soaks] == [4 * 3600.0, 600.0, 1200.0]
    power_on = plan.steps.index(GyroPower(on=True))
    assert plan.steps[power_on + 1] == soaks[1]                 # 10 min after power-on, then the ramp
    assert plan_summary(plan, CFG_X)["total_bench_s"] == pytest.approx(4 * 3600 + 600 + 70 * 60 + 1200, abs=10)


def test_rate_cycle_defaults_match_s001_and_enforce_weak_correlation():
    plan = rate_cycle.build()
    validate_plan(plan, BenchConfig())
    model_ramps = [s for s in kinds(plan, Ramp) if s.part == "model"]
    assert [(s.target_c, s.rate_c_per_min) for s in model_ramps] == [
        (t, r) for r in (2.0, 1.0, 0.5, 0.2, 0.1) for t in (50.0, -20.0)]
    temps = [s.setpoint_c for s in kinds(plan, SetChamber)]
    assert min(temps) == -20.0 and max(temps) == 50.0
    r = rate_cycle.correlation()
    assert abs(r) < 0.4
    assert plan_summary(plan, BenchConfig())["constraints"][0]["r"] == pytest.approx(r)
    # a validation that repeats the modelling cycle is refused before any run
    copy = [rate_cycle.Leg(target_c=t, rate_c_per_min=2.0, hold_min=30.0) for t in (50.0, -20.0)] * 3
    with pytest.raises(PlanError, match=r"\|r\| < 0.4"):
        rate_cycle.build(rate_cycle.Params(validation=copy, initial_soak_h=0.01, cycle_step_c=70.0,
                                           cycle_hold_min=1.0, rates_c_per_min=[2.0] * 3))
    # ... also when someone edits a plan: the engine's validation re-checks the constraint
    good = rate_cycle.build()
    model = [s for s in good.steps if s.part == "model"]
    edited = good.model_copy(update={"steps": [GyroPower(on=True)] + model + [
        s.model_copy(update={"part": "validation"}) for s in model] + [good.steps[-1]]})
    with pytest.raises(PlanError, match=r"correlate with r = (0\.9|1\.0)"):
        validate_plan(edited, BenchConfig())


def test_hrg_defaults_match_s002():
    plan = hrg_calibration.build()
    validate_plan(plan, BenchConfig())
    records = kinds(plan, Record)
    assert [r.labels["temperature_c"] for r in records] == [-40, -30, -20, -10, 0, 10, 20, 30, 40, 50]
    # 5 h per point: 4 h soak + the 5th hour recorded
    assert {s.duration_s for s in kinds(plan, Soak)[:10]} == {4 * 3600.0}
    assert {r.duration_s for r in records} == {3600.0}
    (cool,) = kinds(plan, WaitStable)
    assert cool.record["phase"] == "cool" and kinds(plan, SetChamber)[-1].setpoint_c == -40.0
    assert kinds(plan, Soak)[-1].duration_s == 5 * 3600.0
    (ramp,) = kinds(plan, Ramp)
    assert (ramp.target_c, ramp.rate_c_per_min, ramp.until_probes_c) == (50.0, 1.0, 50.0)


def test_fog_defaults_match_s004():
    plan = fog_startup.build()
    validate_plan(plan, BenchConfig())
    records = kinds(plan, Record)
    points = [-40.0, -25.0, -10.0, 5.0, 20.0, 35.0, 45.0, 60.0]
    assert [r.labels["temperature_c"] for r in records] == points * 2
    assert [r.labels["set"] for r in records] == ["model"] * 8 + ["validation"] * 8
    assert len({r.labels["position"] for r in records}) == 2
    assert {r.duration_s for r in records} == {7200.0}
    # power on just before each record and off after it; soaking unpowered until at temperature
    for r in records:
        i = plan.steps.index(r)
        assert plan.steps[i - 1] == GyroPower(on=True) and plan.steps[i + 1] == GyroPower(on=False)
        assert isinstance(plan.steps[i - 2], WaitStable) and plan.steps[i - 2].probe_tol_c == 1.0


def test_params_refuse_nonsense():
    from pydantic import ValidationError
    with pytest.raises(ValidationError):
        eight_position.Params(soak_h=-1)
    with pytest.raises(ValidationError):
        fog_startup.Params(points_c=[])
    with pytest.raises(ValidationError):
        thermal_ramp.Params(unknown=1)
    with pytest.raises(PlanError, match="outside the allowed range"):
        validate_plan(hrg_calibration.build(hrg_calibration.Params(points_c=[80.0])), BenchConfig())

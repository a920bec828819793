"""Suspend conditions as objects: thresholds a bench config adds (floor / ceiling with a resume
level), the bench's own conditions, and the open suspension's state."""
from __future__ import annotations

import math

import pytest

from bench.config import BenchConfig, SuspendRule
from bench.engine import GyroPower, Plan, Record
from bench.engine.config import EngineConfig
from bench.engine.store import PsuReading
from bench.engine.suspenders import (SuspendCeil, SuspendFloor, Suspension, bench_suspenders, from_rule)
from tests.test_engine_doubles import Bench, Scripted


class Data:
    """A hand-set ``Watched``."""

    def __init__(self) -> None:
        self.cfg = EngineConfig()
        self.link_errors: dict[str, str] = {}
        self.powered_since = None
        self.last_frames_t = None
        self.probe_read_failures = 0
        self.probe_bad: dict[str, int] = {}
        self.probe_fault: dict[str, str] = {}
        self.status = None
        self.psu: PsuReading | None = None
        self.probes: dict[str, float | None] = {}

    def latest_probes(self) -> dict[str, float | None]:
        return self.probes


def test_a_ceiling_trips_above_its_threshold_and_clears_at_its_resume_level():
    data, ceil = Data(), SuspendCeil("psu_amps", 1.2, resume_at=1.0)
    assert ceil.source == "psu" and ceil.check(data, 0.0) is None            # not read yet
    verdicts = []
    for amps in (0.9, 1.2, 1.25, 1.1, None, 1.0, 1.15):
        data.psu = None if amps is None else PsuReading(volts=28.0, amps=amps, on=True)
        verdicts.append(ceil.check(data, 0.0))
    assert verdicts[:2] == [None, None]
    assert verdicts[2] == verdicts[3] == verdicts[4] == "psu_amps 1.25 above 1.2"   # held until 1.0
    assert verdicts[5:] == [None, None]


def test_a_floor_on_a_probe_and_the_rule_that_makes_it():
    rule = SuspendRule(signal="probe:t1", below=-40.0, resume_at=-38.0)
    floor = from_rule(rule)
    assert isinstance(floor, SuspendFloor) and floor.source == "probes" and floor.key == "below:probe:t1"
    data = Data()
    data.probes = {"t1": -40.5}
    assert floor.check(data, 0.0) == "probe:t1 -40.5 below -40"
    data.probes = {"t1": -38.5}
    assert floor.check(data, 0.0) is not None
    data.probes = {"t1": -38.0}
    assert floor.check(data, 0.0) is None


@pytest.mark.parametrize("rule, message", [
    ({"signal": "chamber_pv_c"}, "exactly one of below / above"),
    ({"signal": "chamber_pv_c", "below": 1.0, "above": 2.0}, "exactly one of below / above"),
    ({"signal": "psu_amps", "above": 1.0, "resume_at": 1.5}, "resume_at 1.5 is above the ceiling 1"),
    ({"signal": "psu_amps", "below": 1.0, "resume_at": 0.5}, "resume_at 0.5 is below the floor 1"),
    ({"signal": "gyro_x", "below": 1.0}, "String should match pattern"),
])
def test_bad_rules_are_refused_with_the_reason(rule, message):
    with pytest.raises(ValueError, match=message):
        SuspendRule(**rule)


def test_a_rule_on_an_unknown_probe_is_refused_naming_it():
    with pytest.raises(ValueError, match="suspend.0.signal: 'top' is not a configured probe"):
        BenchConfig(probes={"probes": {"t1": "000000000001"}},
                    suspend=[{"signal": "probe:top", "below": 0.0}])


def test_the_bench_conditions_come_first_then_the_configured_ones():
    config = BenchConfig(suspend=[{"signal": "psu_volts", "below": 27.0}])
    keys = [s.key for s in bench_suspenders(config, ["a", "b"])]
    assert keys == ["gyro_link", "gyro_frames", "probes_link", "probe:a", "probe:b", "chamber_link",
                    "chamber_alarm", "chamber_input", "table_link", "psu_link", "below:psu_volts"]


def test_the_suspension_keeps_every_kind_of_condition_once():
    susp = Suspension.opened(7, 10.0, {"chamber_alarm": "chamber alarm 1"})
    assert susp.add({"chamber_alarm": "chamber alarm 2", "probe:t1": "probe t1 lost: CRC NO"}) == \
        ["probe t1 lost: CRC NO"]
    assert susp.add({"probe:t1": "probe t1 lost: missing"}) == []
    assert susp.reason == "chamber alarm 1; probe t1 lost: CRC NO"
    assert susp.checkpoint() == {"id": 7, "t_from": 10.0, "reason": susp.reason}


def test_a_configured_chamber_floor_suspends_the_run_until_the_air_is_back_at_the_resume_level():
    bench = Bench(settle_s=60.0)
    bench.config = bench.config.model_copy(update={
        "suspend": [SuspendRule(signal="chamber_pv_c", below=20.0, resume_at=22.0)]})
    t0 = bench.clock.now()
    th = bench.thermal

    def setpoint(value):
        def act():
            th.advance()
            th.setpoint = value
        return act

    control = Scripted(bench.clock, [(100.0, setpoint(10.0)), (400.0, setpoint(25.0))])
    plan = Plan(name="f", steps=[GyroPower(on=True), Record(duration_s=600.0, labels={"p": 1})])
    assert bench.engine(control).run("f", plan) == "completed"
    (susp,) = bench.run("f").suspensions
    assert susp["reason"].startswith("chamber_pv_c ") and susp["reason"].endswith(" below 20")
    # air (tau 300 s) from 25 to 10 C: below 19.95 C (the PV reads 0.1 C steps) 300 ln(15/9.95) s after
    # the set point change, seen at the next 5 s status read; at 21.95 C after the change to 25 C, then
    # the 60 s settle
    (down, _), (up, _) = control.fired
    below_at = down + 300.0 * math.log(15.0 / 9.95)
    pv_up = 10.0 + 15.0 * math.exp(-(up - down) / 300.0)
    back_at = up + 300.0 * math.log((25.0 - pv_up) / 3.05)
    assert below_at <= susp["t_from"] - t0 <= below_at + 5.0
    assert back_at + 60.0 <= susp["t_to"] - t0 <= back_at + 65.0

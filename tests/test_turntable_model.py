"""Table physics: interlock, position profile, rate mode, limits, faults (no network)."""
from __future__ import annotations

import math
import threading

import pytest

from bench.sim.turntable import AclError, TableModel, wrap180


def closed_model(**kw) -> TableModel:
    m = TableModel(**kw)
    m.advance_to(0.0)
    for axis in (1, 2):
        m.interlock_close(axis)
    return m


def test_motion_only_with_interlock_closed():
    m = TableModel()
    m.advance_to(0.0)
    with pytest.raises(AclError) as info:
        m.set_mode(1, "P")
    assert info.value.code == -221 and "interlock" in info.value.message
    m.set_position_demand(1, 45.0)           # accepted, stored
    m.advance_to(30.0)
    assert m.angles() == (0.0, 0.0) and m.rates() == (0.0, 0.0)


def test_position_move_profile_respects_limits_and_settles_without_overshoot():
    m = closed_model(rate_limit_dps=20.0, accel_dps2=10.0)
    m.set_mode(1, "P")
    m.set_position_demand(1, 90.0)
    t, peak_rate, max_pos, settled_at = 0.0, 0.0, 0.0, None
    while t < 20.0:
        t += 0.01
        before = m.rates()[0]
        m.advance_to(t)
        rate = m.rates()[0]
        peak_rate = max(peak_rate, abs(rate))
        assert abs(rate - before) <= 10.0 * 0.01 + 1e-9        # acceleration limit
        max_pos = max(max_pos, m.angles()[0])
        if settled_at is None and m.angles()[0] == 90.0 and rate == 0.0:
            settled_at = t
    assert peak_rate == pytest.approx(20.0, abs=1e-9)
    assert max_pos <= 90.0 + 1e-5              # capture-zone ripple far below the 1e-4 deg readback
    # trapezoid: 2 s ramp up (20 deg), 50 deg cruise (2.5 s), braking at 0.9 a (2.22 s, 22.2 deg)
    assert settled_at is not None and 6.5 < settled_at < 7.6
    assert m.angles()[1] == 0.0                               # the other axis did not move


def test_position_takes_the_short_way_round_and_reports_wrapped_angles():
    m = closed_model()
    m.set_mode(1, "P")
    m.set_position_demand(1, 170.0)
    m.advance_to(20.0)
    m.set_position_demand(1, -170.0)        # 20 deg through 180, not 340 deg back
    m.advance_to(20.5)
    assert abs(m.angles()[0]) > 170.0
    m.advance_to(40.0)
    assert m.angles()[0] == -170.0


def test_rate_mode_ramps_at_acceleration_then_integrates_exactly_over_long_gaps():
    m = closed_model(accel_dps2=10.0)
    m.set_mode(2, "R")
    m.set_rate_demand(2, 15.0)
    m.advance_to(1.0)
    assert m.rates()[1] == pytest.approx(10.0)
    m.advance_to(1.6)
    assert m.rates()[1] == 15.0
    # angle after ramp: 15^2/(2*10) = 11.25 deg at t = 1.5 s; then 15 deg/s for 10 h
    t_end = 1.5 + 36000.0
    m.advance_to(t_end)
    assert m.angles()[1] == pytest.approx(wrap180(11.25 + 15.0 * 36000.0), abs=1e-6)


def test_rate_demand_beyond_limit_and_bad_values_are_refused():
    m = closed_model(rate_limit_dps=50.0)
    with pytest.raises(AclError) as info:
        m.set_rate_demand(1, 60.0)
    assert info.value.code == -222
    with pytest.raises(AclError):
        m.set_rate_limit("P", 1, 10_000.0)       # beyond the hardware maximum
    with pytest.raises(AclError):
        m.set_acceleration_demand(1, 0.0)
    with pytest.raises(AclError) as info:
        m.set_rate_limit("X", 1, 10.0)
    assert info.value.code == -224
    with pytest.raises(AclError):
        m.mode(3)


def test_off_mode_and_opening_the_interlock_brake_to_rest():
    m = closed_model(accel_dps2=20.0)
    m.set_mode(1, "R")
    m.set_rate_demand(1, 40.0)
    m.advance_to(5.0)
    m.set_mode(1, "O")
    m.advance_to(6.0)
    assert m.rates()[0] == pytest.approx(20.0)
    m.advance_to(8.0)
    assert m.rates()[0] == 0.0
    m.set_mode(1, "R")
    m.advance_to(12.0)
    assert m.rates()[0] == 40.0                   # the rate demand was kept
    m.interlock_open(1)
    assert m.interlock(1) == "Open" and m.mode(1) == "O"
    m.advance_to(20.0)
    assert m.rates()[0] == 0.0


def test_fault_needs_reset_before_closing_again():
    m = closed_model()
    m.inject_fault(2, "overcurrent")
    assert m.interlock(2) == "Fault"
    with pytest.raises(AclError, match="overcurrent"):
        m.interlock_close(2)
    m.interlock_reset()
    assert m.interlock(2) == "Open"
    m.interlock_close(2)
    assert m.interlock(2) == "Closed"


def test_interlock_close_holds_current_position():
    m = closed_model()
    m.set_mode(1, "R")
    m.set_rate_demand(1, 10.0)
    m.advance_to(10.0)
    m.interlock_open(1)
    m.advance_to(20.0)
    here = m.angles()[0]
    m.interlock_close(1)
    m.set_mode(1, "P")
    m.advance_to(30.0)
    assert m.angles()[0] == here


def test_concurrent_advance_and_reads_are_consistent():
    m = closed_model()
    m.set_mode(1, "R")
    m.set_rate_demand(1, 30.0)
    errors: list[Exception] = []

    def reader():
        try:
            for _ in range(2000):
                assert all(math.isfinite(a) for a in m.angles())
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    thread = threading.Thread(target=reader)
    thread.start()
    for i in range(1, 500):
        m.advance_to(i * 0.01)
    thread.join()
    assert not errors
    assert m.rates()[0] == 30.0

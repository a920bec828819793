"""AcutrolTurntable driver against the simulator over real TCP (both framings) and link faults."""
from __future__ import annotations

import time

import pytest

from bench.clock import AcceleratedClock, SteppedClock
from bench.config import TurntableConfig
from bench.devices.orientation import EIGHT_POSITION_GEOMETRY, EIGHT_POSITIONS, code_at, move_to_orientation
from bench.devices.turntable import AcutrolTurntable, InvalidAxis, TurntableCommandError
from bench.errors import DeviceTimeout, LinkDown, ProtocolError
from bench.interfaces import Turntable
from bench.sim.turntable import IDN, TableModel, TurntableSimulator


def make(framing: str = "line", clock=None, **config):
    clock = clock or SteppedClock(5000.0)
    model = TableModel()
    sim = TurntableSimulator(model, clock, framing=framing).start()
    cfg = TurntableConfig(url=sim.url, framing=framing, timeout_s=config.pop("timeout_s", 1.0), **config)
    table = AcutrolTurntable(cfg, clock)
    return clock, model, sim, table


@pytest.fixture(params=["line", "acutrol_header"])
def rig(request):
    clock, model, sim, table = make(request.param)
    yield clock, model, sim, table
    table.close()
    sim.stop()


def test_driver_implements_the_protocol(rig):
    _, _, _, table = rig
    assert isinstance(table, Turntable)
    assert table.identify() == IDN


def test_move_to_waits_until_in_position(rig):
    clock, model, _, table = rig
    table.interlock_close(1)
    t0 = clock.now()
    state = table.move_to(1, 123.456)
    assert abs(state.position_deg - 123.456) <= 0.01 and abs(state.rate_dps) <= 0.001
    assert model.angles()[0] == pytest.approx(123.456, abs=1e-6)
    # 100 deg/s limit, 50 deg/s^2: at least the triangular-profile time sqrt(4*123.456/50) ~ 3.1 s
    assert clock.now() - t0 >= 3.1
    assert table.mode(1) == "position"


def test_rate_mode_limits_and_off(rig):
    clock, model, _, table = rig
    table.interlock_close(2)
    state = table.rate(2, -30.0, wait=True)
    assert state.rate_dps == pytest.approx(-30.0, abs=0.01)
    clock.advance(2.0)
    assert table.read(2).rate_dps == -30.0
    table.set_rate_limit(2, 20.0, mode="R")
    assert model.rate_limit("R", 2) == 20.0
    with pytest.raises(TurntableCommandError) as info:
        table.rate(2, 25.0)
    assert info.value.code == -222
    table.off(2)
    clock.advance(5.0)
    assert table.read(2).rate_dps == 0.0 and table.mode(2) == "off"


def test_both_axes_in_one_chained_query(rig):
    clock, model, sim, table = rig
    table.interlock_close(1)
    table.interlock_close(2)
    table.move_to(1, 45.0)
    table.rate(2, 12.5, wait=True)
    clock.advance(1.0)
    before = len(sim.received.entries())
    both = table.read_axes([1, 2])
    assert [e.request for e in sim.received.entries()[before:]] == [":Read:Position? 1;Rate? 1;Position? 2;Rate? 2"]
    assert both == {1: table.read(1), 2: table.read(2)}
    assert both[1].position_deg == pytest.approx(45.0, abs=0.01) and both[2].rate_dps == pytest.approx(12.5)
    with pytest.raises(InvalidAxis):
        table.read_axes([1, 3])


def test_acceleration_and_position_rate_limit_slow_the_move(rig):
    clock, model, _, table = rig
    table.interlock_close(1)
    table.move_to(1, 0.5)                     # first motion pushes the configured limits
    table.set_rate_limit(1, 10.0, "P")
    table.set_acceleration(1, 5.0)
    assert model.rate_limit("P", 1) == 10.0 and model.acceleration_demand(1) == 5.0
    t0 = clock.now()
    table.move_to(1, 60.5)
    assert clock.now() - t0 >= 60.0 / 10.0 + 10.0 / 5.0 * 0.5    # cruise + part of the ramps


def test_interlock_blocks_motion(rig):
    _, model, _, table = rig
    with pytest.raises(TurntableCommandError) as info:
        table.move_to(1, 10.0)
    assert info.value.code == -221 and "interlock" in str(info.value).lower()
    assert model.angles()[0] == 0.0
    table.interlock_close(1)
    assert table.interlock_state(1) == "Closed"
    table.interlock_open(1)
    assert table.interlock_state(1) == "Open"
    model.inject_fault(1)
    assert table.interlock_state(1) == "Fault"
    with pytest.raises(TurntableCommandError):
        table.interlock_close(1)
    table.interlock_reset()
    table.interlock_close(1)


def test_bad_axis_and_values_are_refused_before_sending(rig):
    _, _, sim, table = rig
    before = sim.lines_handled
    with pytest.raises(InvalidAxis, match="axis 3"):
        table.read(3)
    with pytest.raises(ValueError, match="finite"):
        table.move_to(1, float("nan"))
    assert sim.lines_handled == before


def test_eight_positions_through_the_driver(rig):
    _, model, _, table = rig
    table.interlock_close(1)
    table.interlock_close(2)
    for code in EIGHT_POSITIONS:
        outer, inner = move_to_orientation(table, code, EIGHT_POSITION_GEOMETRY)
        found, err = code_at(*model.angles(), EIGHT_POSITION_GEOMETRY)
        assert found == code and err < 0.01


def test_move_timeout_is_bounded(rig):
    clock, _, _, table = rig
    table.interlock_close(1)
    with pytest.raises(DeviceTimeout, match="did not reach"):
        table.move_to(1, 170.0, timeout_s=0.5)


def test_accelerated_clock_move():
    clock, model, sim, table = make(clock=AcceleratedClock(speed=50.0))
    try:
        table.interlock_close(1)
        wall0 = time.monotonic()
        table.move_to(1, -90.0)
        # ~3 bench s, 0.06 wall s at 50x: a driver that waited on the wall clock would take 3 wall s
        # or more, whatever the load
        assert time.monotonic() - wall0 < 2.5
        assert model.angles()[0] == pytest.approx(-90.0, abs=0.01)
    finally:
        table.close()
        sim.stop()


# faults -----------------------------------------------------------------------------------------
@pytest.fixture
def line_rig():
    clock, model, sim, table = make("line", timeout_s=0.2)
    yield clock, model, sim, table
    table.close()
    sim.stop()


def test_delayed_reply_times_out_then_recovers(line_rig):
    _, _, sim, table = line_rig
    assert table.identify() == IDN
    sim.faults.delay_s = 0.4
    with pytest.raises(DeviceTimeout, match=r"no reply to '\*IDN\?'"):
        table.identify()
    sim.faults.clear()
    assert table.identify() == IDN          # a late reply on the old link cannot leak in
    assert table.line.stats.timeouts == 1 and table.line.stats.reconnects == 1


def test_dropped_reply_times_out(line_rig):
    _, _, sim, table = line_rig
    sim.faults.drop_next_replies(1)
    with pytest.raises(DeviceTimeout):
        table.read(1)
    assert table.read(1).position_deg == 0.0


def test_link_drop_reconnects_on_next_call(line_rig):
    _, _, sim, table = line_rig
    assert table.identify() == IDN
    sim.faults.drop_link()
    time.sleep(0.05)
    assert table.identify() == IDN
    assert table.line.stats.reconnects == 1 and table.line.stats.link_errors == 1


def test_link_refused_raises_link_down_then_recovers(line_rig):
    _, _, sim, table = line_rig
    assert table.identify() == IDN
    sim.faults.drop_link(refuse_s=0.5)
    time.sleep(0.05)
    with pytest.raises(LinkDown, match=sim.url.split("//")[1]):
        table.identify()
    time.sleep(0.6)
    assert table.identify() == IDN


def test_corrupted_reply_is_a_protocol_error(line_rig):
    _, _, sim, table = line_rig
    sim.faults.corrupt_rate = 1.0
    with pytest.raises(ProtocolError):
        table.interlock_close(1)              # 'OK' with a flipped bit is not 'OK'
    sim.faults.clear()
    assert table.interlock_state(1) == "Closed"


def test_nothing_listening_is_link_down():
    cfg = TurntableConfig(url="socket://127.0.0.1:1", timeout_s=0.2)
    with pytest.raises(LinkDown, match="cannot open socket://127.0.0.1:1"):
        AcutrolTurntable(cfg).identify()

"""``WatlowF4Chamber`` against the simulator over real Modbus TCP and RTU-over-TCP links."""
from __future__ import annotations

import time

import pytest

from bench.clock import SteppedClock
from bench.config import ChamberConfig
from bench.devices.chamber import WatlowF4Chamber
from bench.errors import (DeviceTimeout, IllegalAddress, IllegalValue, LinkDown, ModbusException, PlanError,
                          SensorFault)
from bench.interfaces import Chamber
from bench.sim.chamber import ChamberSimulator
from bench.sim.chamber_physics import ChamberModel
from tests.service_support import SAFETY_S


@pytest.fixture
def clock():
    return SteppedClock(1_700_000_000.0)


def make_sim(clock, **model_kw):
    sim_kw = {k: model_kw.pop(k) for k in ("decimals", "celsius") if k in model_kw}
    model_kw.setdefault("air_c", 25.0)
    model_kw.setdefault("setpoint_c", 25.0)
    return ChamberSimulator(ChamberModel(**model_kw), clock, **sim_kw).start()


def make_driver(sim, transport, clock, baudrate=115200, **cfg):
    """RTU runs over a socket here, so the baud rate only sets pymodbus' polling pace (115200 = quick)."""
    cfg.setdefault("inter_frame_delay_s", 0.0)
    cfg.setdefault("timeout_s", 0.5)
    cfg.setdefault("retries", 0)
    if transport == "tcp":
        config = ChamberConfig(transport="modbus_tcp", address=sim.tcp_address, **cfg)
    else:
        config = ChamberConfig(transport="modbus_rtu", address=sim.rtu_url, baudrate=baudrate, **cfg)
    return WatlowF4Chamber(config, clock=clock)


@pytest.fixture(params=["tcp", "rtu"])
def transport(request):
    return request.param


@pytest.fixture
def sim(clock):
    simulator = make_sim(clock)
    yield simulator
    simulator.stop()


@pytest.fixture
def chamber(sim, transport, clock):
    driver = make_driver(sim, transport, clock)
    yield driver
    driver.close()


def test_reads_and_writes(sim, transport, clock):
    chamber = make_driver(sim, transport, clock, baudrate=9600)
    assert isinstance(chamber, Chamber)
    assert chamber.read_temperature() == pytest.approx(25.0)
    if transport == "rtu":   # register numbers on the wire as-is: 100 -> 0x0064, 300 -> 0x012C
        sim.wire_log.clear()
        chamber.read_setpoint()
        assert ("rx", bytes.fromhex("0103012C0001443F")) in sim.wire_log
        sim.wire_log.clear()
        chamber.read_temperature()          # PV and input error in one FC3 read of 100..101
        assert sim.wire_log[0] == ("rx", bytes.fromhex("01030064000285D4"))
    assert chamber.model_number == 5270
    assert chamber.setpoint_limits() == (pytest.approx(-70.0), pytest.approx(180.0))
    chamber.set_setpoint(-40.5)
    assert chamber.read_setpoint() == pytest.approx(-40.5)
    assert sim.model.setpoint_c == pytest.approx(-40.5)
    clock.advance(120)
    assert chamber.read_temperature() == pytest.approx(15.0)          # 5 C/min cooling limit
    with pytest.raises(IllegalValue, match="register"):
        chamber.set_setpoint(181.0)
    status = chamber.status()
    assert (status.mode, status.alarm, status.input_error, status.power_on) == (0, 0, 0, True)
    assert status.ramp_setpoint_c is None and status.setpoint_c == pytest.approx(-40.5)
    chamber.close()


def test_profile_ramp_hold_resume_and_finish(chamber, sim, clock):
    chamber.ramp_to(45.0, 2.0)
    status = chamber.status()
    assert status.mode == 2 and status.ramp_setpoint_c == pytest.approx(25.0)
    assert sim.read_register(4043) == 20 and sim.read_register(4100) == 1
    clock.advance(300)
    assert sim.read_register(4122) == 350                               # 2 C/min for 5 min
    chamber.hold()
    clock.advance(200)
    status = chamber.status()
    assert status.mode == 3 and status.ramp_setpoint_c == pytest.approx(35.0)
    chamber.resume()
    clock.advance(150)
    assert chamber.status().ramp_setpoint_c == pytest.approx(40.0)
    assert 38.5 < chamber.read_temperature() < 40.0                      # air lags ~1 C
    clock.advance(151)
    status = chamber.status()
    assert status.mode == 0 and status.setpoint_c == pytest.approx(45.0)
    clock.advance(300)
    assert chamber.read_temperature() == pytest.approx(45.0, abs=0.1)


def test_stop_mid_ramp_holds_where_it_is(chamber, sim, clock):
    chamber.ramp_to(-20.0, 3.0)
    clock.advance(200)                                                  # SP 25 -> 15
    chamber.stop()
    status = chamber.status()
    assert status.mode == 0 and status.setpoint_c == pytest.approx(15.0)
    chamber.ramp_to(20.0, 1.0)                                          # a new ramp after a stop
    assert chamber.status().mode == 2
    chamber.ramp_to(30.0, 1.0)                                          # re-ramp while running
    assert chamber.status().mode == 2 and sim.read_register(4044) == 300


def test_ramp_arguments_checked_before_anything_moves(chamber, sim):
    with pytest.raises(PlanError, match="ramp rate"):
        chamber.ramp_to(30.0, 50.0)                                     # > max_ramp_c_per_min
    with pytest.raises(IllegalValue, match="602/603"):
        chamber.ramp_to(500.0, 1.0)
    assert sim.model.mode == 0 and sim.registers.profiles == {}


def test_power_alarm_and_input_error(transport, clock):
    sim = make_sim(clock, alarm_band_c=(-1.0, 1.0), ambient_tau_s=600.0)
    chamber = make_driver(sim, transport, clock)
    try:
        chamber.set_power(False)
        clock.advance(900)
        status = chamber.status()
        assert not status.power_on and status.pv_c < 24.0
        assert status.alarm == 1                                        # low deviation
        chamber.set_power(True)
        clock.advance(600)
        chamber.clear_alarm()
        assert chamber.status().alarm == 0
        sim.faults.input_error = 3
        with pytest.raises(SensorFault, match="101"):
            chamber.read_temperature()
        assert chamber.status().input_error == 3
        sim.faults.input_error = 0
        chamber.clear_alarm()
        assert chamber.read_temperature() == pytest.approx(25.0, abs=0.1)
    finally:
        chamber.close()
        sim.stop()


def test_status_reads_mode_and_event_1_when_due(sim, clock):
    """Constant mode: every status reads PV and set point; mode and event 1 again only after a write of
    ours, every ``status_refresh_s`` (a front-panel change shows within it) and at every call while a
    profile runs (it ends by itself)."""
    chamber = make_driver(sim, "tcp", clock, status_refresh_s=60.0)

    def registers_read(call):
        before = len(sim.received.entries())
        result = call()
        return result, [e.request for e in sim.received.entries()[before:]]

    try:
        chamber.read_setpoint()                         # connected (model, decimals, units read)
        status, regs = registers_read(chamber.status)
        assert regs == ["fc3 @100", "fc3 @200", "fc3 @300", "fc3 @2000"] and status.power_on
        clock.advance(5)
        status, regs = registers_read(chamber.status)
        assert regs == ["fc3 @100", "fc3 @300"] and (status.mode, status.power_on) == (0, True)
        sim.model.set_power(False)                      # the operator, not this driver
        clock.advance(50)
        assert registers_read(chamber.status)[0].power_on          # not due yet: the last value read
        clock.advance(10)
        status, regs = registers_read(chamber.status)
        assert regs == ["fc3 @100", "fc3 @200", "fc3 @300", "fc3 @2000"] and not status.power_on
        chamber.set_power(True)                         # a write of ours: read again at once
        status, regs = registers_read(chamber.status)
        assert "fc3 @2000" in regs and status.power_on
        chamber.ramp_to(26.0, 1.0)                      # a profile of a minute or two
        for _ in range(60):
            clock.advance(5)
            status, regs = registers_read(chamber.status)
            if status.mode == 0:
                break
            assert regs == ["fc3 @100", "fc3 @200", "fc3 @300", "fc3 @2000", "fc3 @4122"]
        assert status.mode == 0 and status.setpoint_c == pytest.approx(26.0)   # the end seen at once
        assert registers_read(chamber.status)[1] == ["fc3 @100", "fc3 @300"]
    finally:
        chamber.close()


def test_modbus_exceptions_are_typed(chamber, sim):
    chamber.read_temperature()                                          # connected
    sim.faults.modbus_exception(code=2)
    with pytest.raises(IllegalAddress, match="register 300") as info:
        chamber.read_setpoint()
    assert info.value.code == 2
    sim.faults.modbus_exception(code=3)
    with pytest.raises(IllegalValue, match="register 2000"):
        chamber.set_power(True)
    sim.faults.modbus_exception(code=6)
    with pytest.raises(ModbusException) as info:
        chamber.read_setpoint()
    assert info.value.code == 6 and not isinstance(info.value, (IllegalAddress, IllegalValue))
    assert chamber.read_setpoint() == pytest.approx(25.0)


def test_missing_and_late_replies_time_out_then_recover(chamber, sim):
    chamber.read_temperature()
    sim.faults.drop_requests = 1
    with pytest.raises(DeviceTimeout, match="register 300"):
        chamber.read_setpoint()
    assert chamber.read_setpoint() == pytest.approx(25.0)
    sim.faults.delay_s = 0.8
    with pytest.raises(DeviceTimeout):
        chamber.read_temperature()
    sim.faults.delay_s = 0.0
    time.sleep(0.4)                                                     # the late reply arrives
    chamber.set_setpoint(30.0)
    assert chamber.read_temperature() == pytest.approx(25.0)            # not confused by it
    assert chamber.read_setpoint() == pytest.approx(30.0)


def test_link_drop_is_link_down_then_reconnects(chamber, sim):
    chamber.read_temperature()
    sim.faults.drop_link(0.5)
    with pytest.raises(LinkDown, match="link lost during read PV"):
        chamber.read_temperature()
    with pytest.raises(LinkDown):                                       # listener gone: cannot reconnect
        chamber.read_temperature()
    time.sleep(0.7)
    assert chamber.read_temperature() == pytest.approx(25.0)


def test_nothing_listening_is_link_down(transport, clock):
    sim = make_sim(clock)
    address = sim.tcp_address if transport == "tcp" else sim.rtu_url
    sim.stop()
    config = (ChamberConfig(transport="modbus_tcp", address=address, timeout_s=0.3) if transport == "tcp"
              else ChamberConfig(transport="modbus_rtu", address=address, timeout_s=0.3))
    chamber = WatlowF4Chamber(config)
    with pytest.raises(LinkDown, match="cannot open"):
        chamber.read_temperature()


def test_wrong_unit_id_times_out(sim, transport, clock):
    chamber = make_driver(sim, transport, clock, unit_id=7, timeout_s=0.3)
    with pytest.raises(DeviceTimeout, match="unit 7"):
        chamber.read_temperature()


def test_host_stepped_ramp(sim, transport, clock):
    chamber = make_driver(sim, transport, clock, ramp_mode="host")
    try:
        chamber.ramp_to(35.0, 2.0)
        assert sim.model.setpoint_c == pytest.approx(25.0) and sim.model.mode == 0
        clock.advance(60)
        assert chamber.ramp_tick() == pytest.approx(27.0)
        assert sim.model.setpoint_c == pytest.approx(27.0)
        chamber.hold()
        clock.advance(120)
        assert chamber.status().ramp_setpoint_c == pytest.approx(27.0)
        chamber.resume()
        clock.advance(90)
        assert chamber.status().ramp_setpoint_c == pytest.approx(30.0)
        clock.advance(400)
        assert chamber.ramp_tick() == pytest.approx(35.0)
        assert not chamber.host_ramp_active and chamber.ramp_tick() is None
        assert chamber.read_setpoint() == pytest.approx(35.0)
    finally:
        chamber.close()


def test_inter_frame_delay_is_respected(sim, clock):
    chamber = make_driver(sim, "tcp", clock, inter_frame_delay_s=0.05)
    try:
        chamber.read_temperature()
        t0 = time.monotonic()
        for _ in range(4):
            chamber.read_setpoint()
        assert time.monotonic() - t0 >= 4 * 0.05
    finally:
        chamber.close()


@pytest.mark.parametrize("decimals,celsius", [(2, True), (0, True), (1, False)])
def test_decimals_and_units_follow_606_and_901(clock, decimals, celsius):
    sim = make_sim(clock, air_c=-12.34, setpoint_c=-12.0, decimals=decimals, celsius=celsius)
    chamber = make_driver(sim, "rtu", clock)
    try:
        expected_step = {2: 0.01, 0: 1.0}.get(decimals, 0.1 * 5 / 9)
        assert chamber.read_temperature() == pytest.approx(-12.34, abs=expected_step / 2 + 1e-9)
        chamber.set_setpoint(-20.0)
        assert sim.model.setpoint_c == pytest.approx(-20.0, abs=expected_step)
    finally:
        chamber.close()
        sim.stop()


def test_profile_ramp_in_accelerated_time():
    from bench.clock import AcceleratedClock
    clock = AcceleratedClock(speed=1200.0)
    sim = make_sim(clock)
    chamber = make_driver(sim, "tcp", clock)
    try:
        chamber.read_temperature()
        t_before = clock.now()
        chamber.ramp_to(45.0, 5.0)                   # 20 C at 5 C/min = 240 bench s = 0.2 wall s
        t_after = clock.now()
        # the ramp started between t_before and t_after, and each status read is bracketed by bench times
        # (a loaded host makes one read cost many bench seconds): "running" was seen no later than the
        # ramp's latest possible end, "done" no earlier than its earliest
        deadline = time.monotonic() + SAFETY_S
        while True:
            t_a = clock.now()
            mode = chamber.status().mode
            t_b = clock.now()
            if mode == 0:
                break
            assert t_a <= t_after + 240.0 + 5.0, f"still ramping {t_a - t_after:.0f} bench s after ramp_to"
            assert time.monotonic() < deadline, "ramp did not finish"
        assert t_b - t_before >= 240.0 - 5.0, f"ramp done {t_b - t_before:.0f} bench s after ramp_to"
        assert chamber.read_setpoint() == pytest.approx(45.0)
    finally:
        chamber.close()
        sim.stop()

"""Chamber simulator: physics of ``ChamberModel`` and the F4 Modbus front-end on the wire.

The wire tests use a raw TCP socket (RTU framing, own CRC) and a plain pymodbus client, so they do
not depend on the driver.
"""
from __future__ import annotations

import math
import socket
import struct
import time

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.framer import FramerType

from bench.clock import SteppedClock
from bench.errors import IllegalValue
from bench.sim.chamber import ChamberSimulator
from bench.sim.chamber_physics import (MODE_CONSTANT, MODE_HELD, MODE_RUNNING, STEP_END, STEP_RAMP_RATE,
                                       STEP_SOAK, ChamberModel, ProfileStep)


def crc16_modbus(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def rtu_frame(body: bytes) -> bytes:
    return body + struct.pack("<H", crc16_modbus(body))


@pytest.fixture
def clock():
    return SteppedClock(1_700_000_000.0)


@pytest.fixture
def sim(clock):
    model = ChamberModel(air_c=25.0, setpoint_c=25.0)
    simulator = ChamberSimulator(model, clock).start()
    yield simulator
    simulator.stop()


def _port(url_or_addr: str) -> int:
    return int(url_or_addr.rsplit(":", 1)[1])


def _rtu_exchange(sim, request: bytes, expect_len: int, timeout: float = 1.0) -> bytes:
    with socket.create_connection(("127.0.0.1", _port(sim.rtu_url)), timeout=timeout) as sock:
        sock.sendall(request)
        data = b""
        deadline = time.monotonic() + timeout
        while len(data) < expect_len and time.monotonic() < deadline:
            try:
                chunk = sock.recv(256)
            except socket.timeout:
                break
            if not chunk:
                break
            data += chunk
        return data


# ---- physics --------------------------------------------------------------------------------

def test_heating_is_rate_limited_then_settles_on_the_setpoint():
    model = ChamberModel(air_c=25.0, heat_rate_c_per_min=5.0, control_tau_s=30.0)
    model.advance_to(0.0)
    model.set_setpoint(85.0)
    model.advance_to(60.0)
    assert model.air_c == pytest.approx(30.0, abs=1e-6)       # 5 C/min, not the 60 C error / 30 s
    model.advance_to(600.0)
    assert model.air_c == pytest.approx(75.0, abs=1e-6)
    model.advance_to(1200.0)
    assert model.air_c == pytest.approx(85.0, abs=0.01)


def test_cooling_rate_is_configurable():
    model = ChamberModel(air_c=25.0, cool_rate_c_per_min=2.0)
    model.advance_to(0.0)
    model.set_setpoint(-40.0)
    model.advance_to(300.0)
    assert model.air_c == pytest.approx(15.0, abs=1e-6)


def test_power_off_drifts_to_ambient_with_time_constant():
    model = ChamberModel(air_c=80.0, setpoint_c=80.0, ambient_c=23.0, ambient_tau_s=1000.0)
    model.advance_to(0.0)
    model.set_power(False)
    model.advance_to(1000.0)
    expected = 23.0 + (80.0 - 23.0) * math.exp(-1.0)
    assert model.air_c == pytest.approx(expected, rel=1e-6)
    model.set_power(True)
    model.advance_to(1060.0)
    assert model.air_c > expected + 4.0


def test_profile_ramp_moves_setpoint_at_rate_and_air_follows_with_small_lag():
    model = ChamberModel(air_c=25.0, control_tau_s=30.0)
    model.advance_to(0.0)
    model.start_profile(1, [ProfileStep(STEP_RAMP_RATE, target_c=45.0, rate_c_per_min=2.0),
                            ProfileStep(STEP_END)])
    assert model.mode == MODE_RUNNING
    model.advance_to(300.0)
    assert model.ramp_setpoint_c == pytest.approx(35.0, abs=1e-9)
    assert 0.5 < model.ramp_setpoint_c - model.air_c < 1.5        # lag ~ rate * tau = 1 C
    model.hold_profile()
    model.advance_to(400.0)
    assert model.mode == MODE_HELD and model.ramp_setpoint_c == pytest.approx(35.0)
    model.resume_profile()
    model.advance_to(700.0)                                         # 500 s of ramp -> target
    assert model.mode == MODE_CONSTANT and model.ramp_setpoint_c is None
    assert model.setpoint_c == pytest.approx(45.0)                  # end action hold keeps the SP
    model.advance_to(1000.0)
    assert model.air_c == pytest.approx(45.0, abs=0.01)


def test_profile_ramp_faster_than_the_plant_lags_and_trips_deviation_alarm():
    model = ChamberModel(air_c=25.0, heat_rate_c_per_min=5.0, alarm_band_c=(-5.0, 5.0))
    model.advance_to(0.0)
    model.start_profile(1, [ProfileStep(STEP_RAMP_RATE, target_c=100.0, rate_c_per_min=20.0),
                            ProfileStep(STEP_END)])
    model.advance_to(120.0)
    assert model.ramp_setpoint_c == pytest.approx(65.0)
    assert model.air_c <= 25.0 + 10.0 + 1e-9
    assert model.alarm == 1                                         # PV below SP by more than 5
    model.clear_alarm()
    assert model.alarm == 1                                         # condition still there


def test_soak_step_and_out_of_limit_target_refused():
    model = ChamberModel(air_c=25.0)
    model.advance_to(0.0)
    with pytest.raises(IllegalValue):
        model.start_profile(1, [ProfileStep(STEP_RAMP_RATE, target_c=500.0, rate_c_per_min=1.0),
                                ProfileStep(STEP_END)])
    model.start_profile(2, [ProfileStep(STEP_SOAK, duration_s=100.0), ProfileStep(STEP_END)])
    model.advance_to(99.0)
    assert model.mode == MODE_RUNNING
    model.advance_to(101.0)
    assert model.mode == MODE_CONSTANT


# ---- wire: raw RTU bytes --------------------------------------------------------------------

def test_rtu_read_pv_exact_bytes(sim):
    request = bytes.fromhex("010300640001C5D5")
    assert rtu_frame(bytes.fromhex("0103 0064 0001".replace(" ", ""))) == request   # our CRC agrees
    reply = _rtu_exchange(sim, request, 7)
    assert len(reply) == 7
    assert reply[:3] == bytes([1, 3, 2])
    assert struct.unpack("<H", reply[5:])[0] == crc16_modbus(reply[:5])
    assert struct.unpack(">h", reply[3:5])[0] == 250                           # 25.0 C, 1 decimal


def test_rtu_unknown_register_gives_exception_02_and_other_unit_is_silent(sim):
    reply = _rtu_exchange(sim, rtu_frame(bytes.fromhex("010300630001")), 5)        # register 99
    assert reply == rtu_frame(bytes([1, 0x83, 2]))
    assert _rtu_exchange(sim, rtu_frame(bytes.fromhex("020300640001")), 5, timeout=0.4) == b""


def test_rtu_write_out_of_range_gives_exception_03(sim):
    reply = _rtu_exchange(sim, rtu_frame(bytes.fromhex("0106012C0BB8")), 5)        # 300 = 300.0 C
    assert reply == rtu_frame(bytes([1, 0x86, 3]))
    assert "outside the set-point limits" in sim.last_refusal


def test_every_defined_register_is_readable_and_gaps_are_02(sim):
    from bench.sim.chamber import _READ_ONLY, _WRITABLE, _runs
    client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=1, retries=0)
    assert client.connect()
    try:
        for start, count in _runs(_READ_ONLY | _WRITABLE):
            for first in range(start, start + count, 100):
                n = min(100, start + count - first)
                reply = client.read_holding_registers(first, count=n, device_id=1)
                assert not reply.isError() and len(reply.registers) == n, (first, n, reply)
            assert client.read_holding_registers(start + count, count=1, device_id=1).exception_code == 2
    finally:
        client.close()


# ---- wire: plain pymodbus clients -----------------------------------------------------------

@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_plain_pymodbus_client_reads_pv_and_writes_setpoint(sim, clock, transport):
    if transport == "tcp":
        client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=1, retries=0)
    else:
        client = ModbusSerialClient(sim.rtu_url, framer=FramerType.RTU, baudrate=9600, timeout=1, retries=0)
    assert client.connect()
    try:
        assert client.read_holding_registers(0, count=1, device_id=1).registers == [5270]
        assert client.read_holding_registers(100, count=1, device_id=1).registers == [250]
        assert client.read_input_registers(100, count=1, device_id=1).registers == [250]   # FC4 shares
        assert not client.write_register(300, 400, device_id=1).isError()
        assert client.read_holding_registers(300, count=1, device_id=1).registers == [400]
        clock.advance(60)
        assert client.read_holding_registers(100, count=1, device_id=1).registers == [300]
        neg = client.convert_to_registers(-405, client.DATATYPE.INT16)
        assert not client.write_register(300, neg[0], device_id=1).isError()
        assert sim.model.setpoint_c == pytest.approx(-40.5)
        assert client.write_register(100, 1, device_id=1).exception_code == 2       # read-only PV
        assert client.read_holding_registers(99, count=1, device_id=1).exception_code == 2
        assert client.write_register(300, 2000, device_id=1).exception_code == 3
        assert client.read_holding_registers(602, count=2, device_id=1).registers == [
            (-700) & 0xFFFF, 1800]
    finally:
        client.close()


def test_profile_edit_registers(sim):
    client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=1, retries=0)
    assert client.connect()
    try:
        def w(reg, value):
            reply = client.write_register(reg, value & 0xFFFF, device_id=1)
            return reply.exception_code if reply.isError() else 0

        def r(reg, count=1):
            return client.read_holding_registers(reg, count=count, device_id=1).registers

        assert w(4000, 3) == 0 and w(4001, 1) == 0
        assert r(4003) == [6]                                   # no such profile/step
        assert w(4003, 2) == 3                                  # cannot edit a missing step
        assert w(4002, 1) == 0 and r(4000) == [3]               # create profile 3 (free)
        assert r(4003) == [STEP_END] and r(1218) == [39]
        assert w(4002, 1) == 0 and r(4000) == [1]               # 3 taken: lowest free number
        assert w(4000, 3) == 0
        assert not client.write_registers(4001, [1, 2], device_id=1).isError()   # insert step 1
        assert r(4003) == [STEP_SOAK]
        assert w(4003, 2) == 0 and w(4043, 30) == 0 and w(4044, 350) == 0
        assert w(4044, 3000) == 3                               # 300 C outside 602/603
        assert w(4043, 0) == 3                                  # zero rate refused
        assert w(4002, 5) == 0                                  # start at step 1
        assert r(200) == [MODE_RUNNING] and r(4100, 2) == [3, 1]
        assert w(4002, 3) == 3                                  # cannot delete the running profile
        assert w(1210, 1) == 0 and r(200) == [MODE_HELD]
        assert w(1209, 1) == 0 and r(200) == [MODE_RUNNING]
        assert w(1217, 1) == 0 and r(200) == [MODE_CONSTANT] and r(4100) == [0]
        assert w(4002, 7) == 3
    finally:
        client.close()


def test_faults_exception_drop_and_delay(sim):
    client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=0.3, retries=0)
    assert client.connect()
    try:
        sim.faults.modbus_exception(code=4, count=2)
        assert client.read_holding_registers(100, count=1, device_id=1).exception_code == 4
        assert client.read_holding_registers(100, count=1, device_id=1).exception_code == 4
        assert client.read_holding_registers(100, count=1, device_id=1).registers == [250]
        sim.faults.drop_replies = 1
        with pytest.raises(Exception):
            client.write_register(300, 300, device_id=1)
        assert sim.model.setpoint_c == pytest.approx(30.0)       # executed, reply lost
    finally:
        client.close()
    seen = sim.faults.requests_seen
    sim.faults.drop_requests = 1
    client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=0.3, retries=0)
    assert client.connect()
    try:
        with pytest.raises(Exception):
            client.write_register(300, 350, device_id=1)
        assert sim.model.setpoint_c == pytest.approx(30.0)       # ignored, not executed
        assert sim.faults.requests_seen == seen + 1
    finally:
        client.close()
    sim.faults.delay_s = 0.2
    client = ModbusTcpClient("127.0.0.1", port=_port(sim.tcp_address), timeout=1.0, retries=0)
    assert client.connect()
    try:
        t0 = time.monotonic()
        assert client.read_holding_registers(100, count=1, device_id=1).registers == [250]
        assert time.monotonic() - t0 >= 0.2
    finally:
        client.close()


def test_link_drop_refuses_connections_then_recovers(sim):
    port = _port(sim.tcp_address)
    sim.faults.drop_link(0.4)
    assert sim.faults.link_down
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
    time.sleep(0.6)
    assert not sim.faults.link_down
    assert sim.tcp_address.endswith(f":{port}")
    reply = _rtu_exchange(sim, bytes.fromhex("010300640001C5D5"), 7)
    assert reply[:3] == bytes([1, 3, 2])


def test_input_error_and_injected_alarm_registers(sim):
    sim.faults.input_error = 5
    assert sim.read_register(101) == 5 and sim.read_register(100) == 0x7FFF
    sim.registers.write(311, 1)
    assert sim.read_register(101) == 5                          # fault still present
    sim.faults.input_error = 0
    sim.registers.write(311, 1)
    assert sim.read_register(101) == 0 and sim.read_register(100) == 250
    sim.faults.alarm = 9
    assert sim.read_register(102) == 9
    sim.faults.alarm = 0
    assert sim.read_register(102) == 9                          # latched
    sim.registers.write(312, 1)
    assert sim.read_register(102) == 0


def test_fahrenheit_and_two_decimals_encoding(clock):
    simulator = ChamberSimulator(ChamberModel(air_c=25.0), clock, decimals=2, celsius=False)
    assert simulator.read_register(100) == 7700                 # 77.00 F
    assert simulator.read_register(606) == 2 and simulator.read_register(901) == 0
    simulator.registers.write(300, 21200)                        # 212.00 F = 100 C
    assert simulator.model.setpoint_c == pytest.approx(100.0)


def test_a_snapshot_taken_while_the_model_lived_in_chamber_py_still_restores():
    """Simulated-bench checkpoints pickle the chamber model's state; the profile objects in it were
    named ``bench.sim.chamber.*`` before the physics moved to ``bench.sim.chamber_physics``."""
    import pickle

    model = ChamberModel(air_c=25.0, control_tau_s=30.0)
    model.advance_to(0.0)
    model.start_profile(1, [ProfileStep(STEP_RAMP_RATE, target_c=45.0, rate_c_per_min=2.0),
                            ProfileStep(STEP_END)])
    model.advance_to(300.0)
    state = {k: v for k, v in vars(model).items() if k != "_lock"}
    old = pickle.dumps(state, protocol=0).replace(b"bench.sim.chamber_physics\n", b"bench.sim.chamber\n")
    assert b"cbench.sim.chamber\n_RunningProfile" in old
    fresh = ChamberModel(air_c=25.0, control_tau_s=30.0)
    vars(fresh).update(pickle.loads(old))
    fresh.advance_to(600.0)
    model.advance_to(600.0)
    assert (fresh.air_c, fresh.ramp_setpoint_c, fresh.mode) == (model.air_c, model.ramp_setpoint_c, model.mode)

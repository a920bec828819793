"""SCPI power supply: model physics, raw SCPI over TCP, driver, faults."""
from __future__ import annotations

import math
import socket
import time

import pytest

from bench.clock import SteppedClock
from bench.config import PsuConfig
from bench.devices.psu import PsuCommandError, ScpiPowerSupply
from bench.errors import DeviceTimeout, LinkDown
from bench.interfaces import PowerSupply
from bench.sim.psu import DEFAULT_IDN, PsuModel, PsuSimulator, ScpiError


# model ------------------------------------------------------------------------------------------
def test_model_cv_then_cc_with_resistive_load():
    m = PsuModel(load_ohm=20.0)
    m.advance_to(100.0)
    m.set_voltage(28.0)
    m.set_current_limit(2.0)
    assert m.regulation() == "OFF" and m.output_voltage() == 0.0
    m.set_output(True)
    assert m.on_since == 100.0 and m.output_on
    assert m.regulation() == "CV"
    assert m.output_voltage() == 28.0 and m.output_current() == pytest.approx(1.4)
    m.set_current_limit(1.0)                    # 28 V / 20 ohm = 1.4 A > 1 A -> CC
    assert m.regulation() == "CC"
    assert m.output_current() == 1.0 and m.output_voltage() == pytest.approx(20.0)


def test_model_constant_current_sink_and_power_on_time():
    m = PsuModel(load_ohm=math.inf, load_current_a=0.6)
    m.advance_to(10.0)
    m.set_voltage(28.0)
    m.set_current_limit(1.5)
    m.set_output(True)
    m.advance_to(70.0)
    assert m.on_since == 10.0                   # not moved by later advances
    assert m.output_current() == pytest.approx(0.6)
    m.set_output(True)                          # already on: on_since unchanged
    assert m.on_since == 10.0
    m.set_output(False)
    assert m.on_since is None and m.output_current() == 0.0
    m.advance_to(80.0)
    m.set_output(True)
    assert m.on_since == 80.0


def test_model_refuses_out_of_range_and_needs_a_time_before_power_on():
    m = PsuModel(max_voltage_v=30.0, max_current_a=3.0)
    with pytest.raises(ScpiError):
        m.set_voltage(31.0)
    with pytest.raises(ScpiError):
        m.set_current_limit(-0.1)
    with pytest.raises(RuntimeError, match="advance_to"):
        m.set_output(True)
    with pytest.raises(ValueError, match="resistance"):
        m.set_load(resistance_ohm=0.0)


# raw SCPI ---------------------------------------------------------------------------------------
@pytest.fixture
def sim():
    clock = SteppedClock(1000.0)
    model = PsuModel(load_ohm=56.0)
    server = PsuSimulator(model, clock).start()
    yield clock, model, server
    server.stop()


class Raw:
    def __init__(self, address):
        self.sock = socket.create_connection(address, timeout=1.0)
        self.file = self.sock.makefile("rwb")

    def send(self, text: str) -> None:
        self.file.write(text.encode() + b"\n")
        self.file.flush()

    def ask(self, text: str) -> str:
        self.send(text)
        line = self.file.readline()
        assert line.endswith(b"\n"), line
        return line[:-1].decode()

    def sync(self) -> None:
        """Settings are silent: a query after them proves they were processed."""
        assert self.ask("*OPC?") == "1"

    def close(self):
        self.file.close()
        self.sock.close()


@pytest.fixture
def raw(sim):
    link = Raw(sim[2].address)
    yield link
    link.close()


def test_settings_give_no_reply_queries_do(sim, raw):
    _, model, _ = sim
    raw.send("VOLT 28")
    raw.send("CURR 1.5")
    raw.sync()                                 # the first line read is the query's: settings were silent
    assert raw.ask("*IDN?") == DEFAULT_IDN
    assert model.voltage_setting == 28.0 and model.current_limit == 1.5


def test_short_long_forms_optional_nodes_and_units(sim, raw):
    _, model, _ = sim
    raw.send(":SOURce:VOLTage:LEVel:IMMediate:AMPLitude 12.5")
    raw.sync()
    assert model.voltage_setting == 12.5
    raw.send("volt:lev 1500 mV")
    raw.sync()
    assert model.voltage_setting == 1.5
    raw.send("current 250mA")
    raw.sync()
    assert model.current_limit == 0.25
    assert raw.ask("SOUR:VOLT?;:CURR?") == "1.500000E+00;2.500000E-01"
    assert raw.ask("SYST:ERR?") == '0,"No error"'
    raw.send("VOLTA 3")                                  # neither short nor long form
    assert raw.ask("SYST:ERR?") == '-113,"Undefined header"'


def test_output_and_measurements(sim, raw):
    raw.send("VOLT 28;CURR 1;OUTP ON")
    assert raw.ask("OUTP?;:MEAS:VOLT?;:MEAS:CURR?") == "1;2.800000E+01;5.000000E-01"
    assert raw.ask("MEASure:SCALar:CURRent:DC?") == "5.000000E-01"
    raw.send("OUTPut:STATe OFF")
    assert raw.ask("OUTP?") == "0"


def test_error_queue_codes_order_and_clear(sim, raw):
    _, model, server = sim
    raw.send("FOO 1")
    raw.send("VOLT 100")                    # max 60 V
    raw.send("VOLT abc")
    raw.send("OUTP MAYBE")
    raw.sync()
    assert model.voltage_setting == 0.0
    assert raw.ask("SYST:ERR?") == '-113,"Undefined header"'
    assert raw.ask("SYST:ERR:NEXT?") == '-222,"Data out of range"'
    assert raw.ask("SYST:ERR?") == '-104,"Data type error"'
    raw.send("*CLS")
    assert raw.ask("SYST:ERR?") == '0,"No error"'
    for _ in range(25):
        raw.send("NOPE")
    raw.sync()
    queue = server.error_queue()
    assert len(queue) == 20 and queue[-1] == -350 and queue[0] == -113


def test_relative_path_rule(sim, raw):
    # after MEAS:VOLT? the path is MEAS:, so "MEAS:CURR?" becomes MEAS:MEAS:CURR? -> error
    raw.send("VOLT 5;OUTP ON")
    assert raw.ask("MEAS:VOLT?;CURR?") == "5.000000E+00;8.928571E-02"     # 5 V / 56 ohm
    assert raw.ask("MEAS:VOLT?;MEAS:CURR?") == "5.000000E+00"
    assert raw.ask("SYST:ERR?") == '-113,"Undefined header"'


def test_power_on_time_follows_the_bench_clock(sim, raw):
    clock, model, _ = sim
    clock.advance(50.0)
    raw.send("OUTP ON")
    raw.sync()
    assert model.on_since == 1050.0


# driver -----------------------------------------------------------------------------------------
@pytest.fixture
def psu(sim):
    _, _, server = sim
    driver = ScpiPowerSupply(PsuConfig(url=server.url, timeout_s=0.3, voltage_v=28.0, current_limit_a=1.5))
    yield driver
    driver.close()


def test_driver_round_trip(sim, psu):
    _, model, _ = sim
    assert isinstance(psu, PowerSupply)
    assert psu.identify() == DEFAULT_IDN
    psu.apply_config()
    assert model.voltage_setting == 28.0 and model.current_limit == 1.5
    assert psu.output_state() is False
    psu.output(True)
    assert psu.output_state() is True and model.output_on
    assert psu.measure_voltage() == 28.0
    assert psu.measure_current() == pytest.approx(0.5)
    model.set_load(resistance_ohm=10.0)          # 2.8 A wanted > 1.5 A limit -> CC
    assert psu.measure_current() == 1.5 and psu.measure_voltage() == pytest.approx(15.0)
    psu.output(False)
    assert psu.measure_voltage() == 0.0


def test_driver_raises_with_the_scpi_error(sim, psu):
    with pytest.raises(PsuCommandError) as info:
        psu.set_voltage(75.0)
    assert info.value.code == -222 and "VOLT 75.0000" in str(info.value) and "Data out of range" in str(info.value)
    assert psu.identify() == DEFAULT_IDN         # the queue was drained
    with pytest.raises(ValueError):
        psu.set_current_limit(-1.0)


def test_driver_unanswered_query_reports_the_queued_error(sim, psu):
    with pytest.raises(PsuCommandError) as info:
        psu.query("MEAS:POWER?")
    assert info.value.code == -113


def test_driver_timeout_and_link_faults(sim, psu):
    _, _, server = sim
    assert psu.identify() == DEFAULT_IDN
    server.faults.drop_next_replies(1)
    with pytest.raises(DeviceTimeout):
        psu.identify()
    assert psu.identify() == DEFAULT_IDN
    server.faults.drop_link()
    time.sleep(0.05)
    assert psu.output_state() is False           # reconnected on this call
    server.faults.drop_link(refuse_s=0.4)
    time.sleep(0.05)
    with pytest.raises(LinkDown):
        psu.identify()
    time.sleep(0.5)
    assert psu.identify() == DEFAULT_IDN
    assert psu.line.stats.reconnects >= 2

"""Every DS18B20 failure signature is rejected, counted per probe and kind, and good reads resume."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from bench.clock import SteppedClock
from bench.config import ProbeConfig
from bench.devices.ds18b20 import W1ProbeArray
from bench.sim.w1 import W1TreeSimulator
from tests.test_ds18b20_w1 import PROBES, TableSource

EXPECTED_LINES = {
    "crc": ("ff ff ff ff ff ff ff ff ff : crc=c9 NO", "72 01 4b 46 7f ff 0e 10 57 t=-62"),
    "power_on_85": ("50 05 4b 46 7f ff 0c 10 1c : crc=1c YES", "50 05 4b 46 7f ff 0c 10 1c t=85000"),
    "all_zero": ("00 00 00 00 00 00 00 00 00 : crc=00 YES", "00 00 00 00 00 00 00 00 00 t=0"),
    "failed_conversion": ("ff 07 4b 46 7f ff 0c 10 a6 : crc=a6 YES", "ff 07 4b 46 7f ff 0c 10 a6 t=127937"),
}


@pytest.fixture
def bench(tmp_path):
    clock = SteppedClock(5000.0)
    sim = W1TreeSimulator(TableSource({"t1": 23.125, "t2": 21.0}), clock, tmp_path, PROBES)
    sim.update()
    probes = W1ProbeArray(ProbeConfig(w1_root=str(tmp_path), probes=PROBES))
    return clock, sim, probes, tmp_path


@pytest.mark.parametrize("kind", list(EXPECTED_LINES))
def test_fault_signature_exact_and_rejected(bench, kind):
    clock, sim, probes, root = bench
    sim.faults.set("t1", kind)
    sim.update()
    text = (root / "28-0123456789ab" / "w1_slave").read_text()
    assert text == "\n".join(EXPECTED_LINES[kind]) + "\n"
    t1, t2 = probes.read_all()
    assert t1.celsius is None and t1.fault.startswith(f"{kind}:") and "28-0123456789ab" in t1.fault
    assert t2.celsius == 21.0 and t2.fault is None
    assert probes.fault_counts["t1"] == {kind: 1} and not probes.fault_counts["t2"]
    assert (root / "28-0123456789ab" / "temperature").exists() == (kind != "crc")


def test_vanished_device_comes_back(bench):
    clock, sim, probes, root = bench
    sim.faults.set("t1", "vanished", duration_s=2.0)
    sim.update()
    assert not (root / "28-0123456789ab").exists()
    r = probes.read_one("t1")
    assert r.celsius is None and r.fault.startswith("vanished:")
    clock.advance(2.5)
    sim.update()
    assert probes.read_one("t1").celsius == 23.125
    assert probes.fault_counts["t1"] == {"vanished": 1} and probes.good_reads["t1"] == 1


def test_counts_accumulate_per_probe_and_kind(bench):
    clock, sim, probes, root = bench
    plan = ["crc", "crc", "all_zero", "power_on_85", "failed_conversion", None, "vanished", None]
    for kind in plan:
        if kind is None:
            sim.faults.clear("t2")
        else:
            sim.faults.set("t2", kind)
        sim.update()
        probes.read_all()
    assert probes.fault_counts["t2"] == {"crc": 2, "all_zero": 1, "power_on_85": 1, "failed_conversion": 1,
                                         "vanished": 1}
    assert probes.good_reads["t2"] == 2 and probes.good_reads["t1"] == len(plan)
    assert sum(probes.fault_totals().values()) == 6


def test_a_true_85_degrees_is_not_a_power_on_value(tmp_path):
    sim = W1TreeSimulator(TableSource({"t1": 85.0, "t2": 20.0}), SteppedClock(), tmp_path, PROBES)
    sim.update()
    text = (tmp_path / "28-0123456789ab" / "w1_slave").read_text()
    assert text.startswith("50 05 4b 46 7f ff 10 10 ")          # byte 6 = 0x10, not 0x0c
    assert W1ProbeArray(ProbeConfig(w1_root=str(tmp_path), probes=PROBES)).read_one("t1").celsius == 85.0


def test_crc_mismatch_hidden_behind_yes_is_caught(bench):
    clock, sim, probes, root = bench
    path = root / "28-0123456789ab" / "w1_slave"
    path.write_text("72 01 4b 46 7f ff 0e 10 58 : crc=58 YES\n72 01 4b 46 7f ff 0e 10 58 t=23125\n")
    r = probes.read_one("t1")
    assert r.celsius is None and r.fault.startswith("crc:") and "computed 57" in r.fault
    path.write_text("garbage\n")
    assert probes.read_one("t1").fault.startswith("malformed:")
    path.write_text("72 01 4b 46 7f ff 0e 10 57 : crc=57 YES\n72 01 4b 46 7f ff 0e 10 57 t=23000\n")
    assert probes.read_one("t1").fault.startswith("malformed:")
    assert probes.fault_counts["t1"] == {"crc": 1, "malformed": 2}


def test_w1thermsensor_cannot_tell_the_faults_apart(bench, monkeypatch):
    """The measured reason (see bench/devices/ds18b20.py) for using our own parser."""
    monkeypatch.setenv("W1THERMSENSOR_NO_KERNEL_MODULE", "1")
    from w1thermsensor import Sensor, W1ThermSensor
    from w1thermsensor.errors import SensorNotReadyError

    clock, sim, probes, root = bench
    monkeypatch.setattr(W1ThermSensor, "BASE_DIRECTORY", Path(root))
    sensor = W1ThermSensor(Sensor.DS18B20, "0123456789ab")
    assert sensor.get_temperature() == 23.125
    seen = {}
    for kind in ("crc", "all_zero", "failed_conversion"):
        sim.faults.set("t1", kind)
        sim.update()
        try:
            seen[kind] = sensor.get_temperature()
        except SensorNotReadyError as exc:
            seen[kind] = type(exc)
    assert seen["crc"] is seen["all_zero"] is SensorNotReadyError     # one error for two kinds
    assert seen["failed_conversion"] == 127.9375                        # accepted as a reading
    assert os.environ["W1THERMSENSOR_NO_KERNEL_MODULE"] == "1"

"""DS18B20 w1 sysfs format: bytes, CRC-8, t= with C semantics, the simulated tree and its timing."""
from __future__ import annotations

import shutil
import time

import pytest

from bench.clock import SteppedClock
from bench.config import ProbeConfig
from bench.devices.ds18b20 import (W1ProbeArray, c_div, classify, dallas_crc8, millidegrees, normalise_serial,
                                   parse_w1_slave)
from bench.errors import DataFormatError, ProtocolError
from bench.sim.w1 import W1TreeSimulator, good_scratchpad, w1_slave_text

PROBES = {"t1": "0123456789ab", "t2": "28-00000A1B2C3D"}


class TableSource:
    def __init__(self, temps):
        self.temps = dict(temps)
        self.advanced = []

    def advance_to(self, t):
        self.advanced.append(t)

    def probe_temperatures(self):
        return dict(self.temps)


def test_dallas_crc8_check_vectors():
    assert dallas_crc8(bytes.fromhex("72014b467fff0e10")) == 0x57
    assert dallas_crc8(b"\xff" * 8) == 0xC9
    assert dallas_crc8(bytes(8)) == 0x00


def test_c_truncating_division_differs_from_python_floor():
    assert c_div(-1000, 16) == -62 and -1000 // 16 == -63
    assert millidegrees(-1) == -62                     # 0xFFFF: the kernel's bus-open t=-62
    assert millidegrees(0x07FF) == 127937
    assert millidegrees(-3) == -187                    # -187.5 truncates toward zero


def test_reference_line_reproduced_exactly():
    pad = good_scratchpad(23.125)
    assert pad.hex(" ") == "72 01 4b 46 7f ff 0e 10 57"
    text, ok = w1_slave_text(pad, pad)
    assert ok and text == "72 01 4b 46 7f ff 0e 10 57 : crc=57 YES\n72 01 4b 46 7f ff 0e 10 57 t=23125\n"


@pytest.mark.parametrize("celsius, hexbytes, t", [
    (-10.125, "5e ff", -10125),
    (-0.0625, "ff ff", -62),
    (-55.0, "90 fc", -55000),
    (125.0, "d0 07", 125000),
    (0.03, "00 00", 0),            # quantised to 0.0625: 0.03 -> 0
    (25.04, "91 01", 25062),       # 25.04 / 0.0625 = 400.64 -> 401 -> 25.0625 -> t=25062
])
def test_negative_and_edge_temperatures(celsius, hexbytes, t):
    pad = good_scratchpad(celsius)
    assert pad[:2].hex(" ") == hexbytes
    assert dallas_crc8(pad[:8]) == pad[8]
    text, ok = w1_slave_text(pad, pad)
    assert ok and text.endswith(f" t={t}\n")
    read = parse_w1_slave(text)
    assert classify(read)[0] == pytest.approx(int.from_bytes(pad[:2], "little", signed=True) / 16)


def test_lower_resolution_config_byte_and_masking():
    pad = good_scratchpad(23.1875, bits=10)            # 371 counts; 10 bit leaves 2 low bits undefined
    assert pad[4] == 0x3F
    assert classify(parse_w1_slave(w1_slave_text(pad, pad)[0]))[0] == 23.0
    # bits the device left undefined are masked by the reader even if set
    noisy = bytes([pad[0] | 0x03]) + pad[1:8]
    noisy += bytes([dallas_crc8(noisy)])
    assert classify(parse_w1_slave(w1_slave_text(noisy, noisy)[0]))[0] == 23.0


def test_tree_layout_files_and_atomic_rate_limited_updates(tmp_path):
    clock = SteppedClock(1000.0)
    source = TableSource({"t1": -10.125, "t2": 36.6})
    sim = W1TreeSimulator(source, clock, tmp_path, PROBES, conversion_s=0.75)
    sim.start()
    try:
        d1 = tmp_path / "28-0123456789ab"
        assert (d1 / "w1_slave").read_text() == (
            "5e ff 4b 46 7f ff 02 10 b6 : crc=b6 YES\n5e ff 4b 46 7f ff 02 10 b6 t=-10125\n")
        assert (d1 / "temperature").read_text() == "-10125\n"
        assert (tmp_path / "28-00000a1b2c3d" / "w1_slave").exists()
        updates = sim.updates
        source.temps["t1"] = 5.0
        clock.advance(0.5)                              # less than one conversion: no rewrite
        time.sleep(0.1)
        assert sim.updates == updates and "t=-10125" in (d1 / "w1_slave").read_text()
        clock.advance(0.3)
        deadline = time.monotonic() + 3
        while sim.updates == updates and time.monotonic() < deadline:
            time.sleep(0.01)
        assert (d1 / "w1_slave").read_text().endswith("t=5000\n")
        assert source.advanced[-1] == clock.now()
        assert not [p for p in d1.iterdir() if p.name.startswith(".")]   # no temp files left behind
        probes = W1ProbeArray(ProbeConfig(w1_root=str(tmp_path), probes=PROBES))
        assert [(r.name, r.serial, r.celsius, r.fault) for r in probes.read_all()] == [
            ("t1", "0123456789ab", 5.0, None), ("t2", "00000a1b2c3d", 36.625, None)]
    finally:
        sim.stop()


def test_serials_and_malformed_text_give_clear_errors(tmp_path):
    assert normalise_serial("28-0123456789AB") == "0123456789ab"
    with pytest.raises(DataFormatError, match="probes.t9"):
        W1ProbeArray(ProbeConfig(w1_root=str(tmp_path), probes={"t9": "12345"}))
    with pytest.raises(ProtocolError, match="line 1"):
        parse_w1_slave("72 01 4b : crc=57 YES\n72 01 4b 46 7f ff 0e 10 57 t=23125\n")
    with pytest.raises(ProtocolError, match="1 line"):
        parse_w1_slave("72 01 4b 46 7f ff 0e 10 57 : crc=57 YES\n")
    with pytest.raises(KeyError, match="t2"):
        W1TreeSimulator(TableSource({"t1": 20}), SteppedClock(), tmp_path, PROBES).update()


def test_same_text_is_not_parsed_again_but_counted_again(tmp_path, monkeypatch):
    """A probe's file changes only with a new conversion: the same text gives the same reading (and the
    same fault, counted at every read) without being parsed again; a new text is parsed."""
    from bench.config import ProbeConfig
    from bench.devices import ds18b20
    from bench.sim.w1 import BUS_OPEN_SCRATCHPAD, good_scratchpad, w1_slave_text

    serial = "0000a1b2c3d4"
    path = tmp_path / f"28-{serial}" / "w1_slave"
    path.parent.mkdir()
    arr = ds18b20.W1ProbeArray(ProbeConfig(w1_root=str(tmp_path), probes={"t1": serial}))
    parsed = []
    real_parse = ds18b20.parse_w1_slave
    monkeypatch.setattr(ds18b20, "parse_w1_slave", lambda text: parsed.append(text) or real_parse(text))
    path.write_text(w1_slave_text(BUS_OPEN_SCRATCHPAD, bytes(9))[0])
    assert [arr.read_one("t1").celsius for _ in range(3)] == [None] * 3
    assert arr.fault_counts["t1"][ds18b20.FAULT_CRC] == 3 and len(parsed) == 1
    path.write_text(w1_slave_text(good_scratchpad(21.5), bytes(9))[0])
    assert [arr.read_one("t1").celsius for _ in range(2)] == [21.5, 21.5]
    assert arr.good_reads["t1"] == 2 and len(parsed) == 2
    path.write_text("garbage\n")
    assert arr.read_one("t1").fault.startswith(f"{ds18b20.FAULT_MALFORMED}: {path}: w1_slave has 1 line")


def test_a_tree_removed_from_outside_is_written_again_at_the_next_conversion(tmp_path):
    from bench.clock import LockstepClock

    clock = LockstepClock(1000.0, pace=None)
    source = TableSource({"t1": 21.5, "t2": 22.0})
    root = tmp_path / "w1"
    sim = W1TreeSimulator(source, clock, root, PROBES)
    sim.start()
    clock.serve("w1", sim.serve)
    clock.advance_to(1002.0)
    d1 = root / "28-0123456789ab"
    text = (d1 / "w1_slave").read_text()
    # right after a conversion (the same timestamp tick as the tree's last change) and later, the same
    # temperatures: the files are only written because they are gone
    for gone in (d1, d1, root):
        shutil.rmtree(gone)
        clock.advance_to(clock.now() + 2.0)
        assert (d1 / "w1_slave").read_text() == text
        assert (root / "28-00000a1b2c3d" / "w1_slave").exists()

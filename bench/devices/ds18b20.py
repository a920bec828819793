"""DS18B20 probes read through the Linux ``w1_therm`` sysfs files.

Facts used (reference section 4): directory ``<w1_root>/28-<12 hex serial>/``; ``w1_slave`` is
two lines, e.g.::

    72 01 4b 46 7f ff 0e 10 57 : crc=57 YES
    72 01 4b 46 7f ff 0e 10 57 t=23125

Line 1 holds the 9 scratchpad bytes just read and the *computed* Dallas CRC-8 of bytes 0..7
with YES/NO; line 2 holds the last good retained bytes and ``t=`` in millidegrees computed from
the current read as ``(int16)(msb<<8|lsb) * 1000 / 16`` with C (truncating) division.  Scratchpad:
0 temp LSB, 1 temp MSB, 2 TH, 3 TL, 4 config (0 R1 R0 1 1 1 1 1; 0x7F = 12 bit), 5 0xFF,
6 reserved (0x0C at power-up), 7 0x10, 8 CRC.  At 9/10/11-bit resolution the low 3/2/1 bits of
the temperature are undefined and are masked off here (resolution taken from byte 4).

Rejected readings (``ProbeReading.celsius is None``; ``fault`` starts with the kind), counted
per probe and kind in ``fault_counts``:

===================== =======================================================================
kind                  signature
===================== =======================================================================
``vanished``          directory or file gone (``OSError``), device dropped off the bus
``malformed``         text not in the kernel format, or ``t=`` disagreeing with the bytes
``all_zero``          ``00`` x 9: passes the CRC (CRC-8 of zeros is 0) - bus shorted/unplugging
``crc``               line 1 says NO, or the CRC-8 we compute disagrees (bus open: ``ff`` x 9)
``power_on_85``       temp register 0x0550 (85.000 C) with byte 6 == 0x0C: power-on value,
                      no conversion happened (valid CRC!)
``failed_conversion`` temp register 0x07FF (127.94 C): failed conversion (parasite power)
``out_of_range``      outside the sensor's -55..+125 C
===================== =======================================================================

Why not ``w1thermsensor`` (2.3.0, installed; checked by running it on this simulator's tree,
see tests/test_ds18b20_faults.py::test_w1thermsensor_cannot_tell_the_faults_apart):
it raises the same ``SensorNotReadyError`` for a CRC NO and an all-zero read (the two kinds
must be counted apart), returns 127.9375 for a failed conversion without complaint, rejects
*any* 85.0 value without looking at byte 6, and parses line 2 (the retained bytes) rather than
the current read.  The format is two lines; a 40-line parser is clearer than wrapping it.
"""
from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from bench.config import ProbeConfig
from bench.errors import DataFormatError, ProtocolError
from bench.interfaces import ProbeReading

FAMILY_PREFIX = "28-"
FAULT_VANISHED = "vanished"
FAULT_MALFORMED = "malformed"
FAULT_ALL_ZERO = "all_zero"
FAULT_CRC = "crc"
FAULT_POWER_ON = "power_on_85"
FAULT_FAILED_CONVERSION = "failed_conversion"
FAULT_OUT_OF_RANGE = "out_of_range"

POWER_ON_RAW = 0x0550
FAILED_CONVERSION_RAW = 0x07FF
MIN_C, MAX_C = -55.0, 125.0


def _crc8_bitwise(data: bytes) -> int:
    crc = 0
    for byte in data:
        for _ in range(8):
            mix = (crc ^ byte) & 1
            crc >>= 1
            if mix:
                crc ^= 0x8C
            byte >>= 1
    return crc


_CRC8_TABLE = tuple(_crc8_bitwise(bytes([i])) for i in range(256))


def dallas_crc8(data: bytes) -> int:
    """Dallas/Maxim CRC-8: poly x^8+x^5+x^4+1 (0x8C reflected), init 0, LSB first, no final xor
    (one table look-up per byte; the table is the bitwise definition applied to each byte value)."""
    crc = 0
    for byte in data:
        crc = _CRC8_TABLE[crc ^ byte]
    return crc


def c_div(a: int, b: int) -> int:
    """Integer division truncating toward zero, as C does (Python's // floors)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


def raw_temperature(scratchpad: bytes) -> int:
    """Signed 16-bit temperature register from scratchpad bytes 0 (LSB) and 1 (MSB)."""
    return int.from_bytes(scratchpad[0:2], "little", signed=True)


def millidegrees(raw: int) -> int:
    """The kernel's ``t=`` value for a DS18B20 register value."""
    return c_div(raw * 1000, 16)


def resolution_bits(config_byte: int) -> int:
    return 9 + ((config_byte >> 5) & 0x03)


def normalise_serial(serial: str, where: str = "probe") -> str:
    """``28-0123456789ab`` or ``0123456789AB`` -> ``0123456789ab``; DataFormatError otherwise."""
    text = serial.strip().lower()
    if text.startswith(FAMILY_PREFIX):
        text = text[len(FAMILY_PREFIX):]
    if not re.fullmatch(r"[0-9a-f]{12}", text):
        raise DataFormatError(f"DS18B20 serial {serial!r} is not 12 hex digits (optionally prefixed '28-')",
                              column=where)
    return text


@dataclass(frozen=True)
class W1SlaveRead:
    current: bytes        # line 1: the 9 bytes just read
    crc_yes: bool         # line 1 verdict
    reported_crc: int     # line 1 crc= (computed by the kernel)
    retained: bytes       # line 2: last good bytes
    t_milli: int          # line 2 t=


_HEX9 = r"((?:[0-9a-f]{2} ){9})"
_LINE1 = re.compile(_HEX9 + r": crc=([0-9a-f]{2}) (YES|NO)")
_LINE2 = re.compile(_HEX9 + r"t=(-?\d+)")


def parse_w1_slave(text: str) -> W1SlaveRead:
    """Parse the two ``w1_slave`` lines; ProtocolError when the text is not in kernel format."""
    lines = text.splitlines()
    if len(lines) < 2:
        raise ProtocolError(f"w1_slave has {len(lines)} line(s), expected 2: {text!r}")
    m1 = _LINE1.fullmatch(lines[0].rstrip())
    m2 = _LINE2.fullmatch(lines[1].rstrip())
    if not m1:
        raise ProtocolError(f"w1_slave line 1 not in kernel format: {lines[0]!r}")
    if not m2:
        raise ProtocolError(f"w1_slave line 2 not in kernel format: {lines[1]!r}")
    return W1SlaveRead(bytes.fromhex(m1.group(1)), m1.group(3) == "YES", int(m1.group(2), 16),
                       bytes.fromhex(m2.group(1)), int(m2.group(2)))


_ALL_ZERO = bytes(9)


def classify(read: W1SlaveRead) -> tuple[float | None, str | None, str]:
    """(celsius, None, "") for a good read, else (None, fault kind, detail)."""
    cur = read.current
    if cur == _ALL_ZERO:
        return None, FAULT_ALL_ZERO, f"scratchpad {cur.hex(' ')} (bus shorted or probe unplugging)"
    computed = dallas_crc8(cur[:8])
    if not read.crc_yes or computed != cur[8] or read.reported_crc != computed:
        return None, FAULT_CRC, (f"scratchpad {cur.hex(' ')}, kernel says crc={read.reported_crc:02x} "
                                 f"{'YES' if read.crc_yes else 'NO'}, computed {computed:02x}")
    raw = raw_temperature(cur)
    if raw == POWER_ON_RAW and cur[6] == 0x0C:
        return None, FAULT_POWER_ON, f"85.000 C power-on value (byte 6 = 0x0c), scratchpad {cur.hex(' ')}"
    if raw == FAILED_CONVERSION_RAW:
        return None, FAULT_FAILED_CONVERSION, f"127.94 C (0x07ff) failed conversion, scratchpad {cur.hex(' ')}"
    if read.t_milli != millidegrees(raw):
        return None, FAULT_MALFORMED, (f"t={read.t_milli} disagrees with bytes {cur.hex(' ')} "
                                       f"({millidegrees(raw)})")
    undefined = 12 - resolution_bits(cur[4])
    celsius = ((raw >> undefined) << undefined) / 16.0
    if not MIN_C <= celsius <= MAX_C:
        return None, FAULT_OUT_OF_RANGE, f"{celsius} C outside {MIN_C}..{MAX_C} C"
    return celsius, None, ""


def _read_text(path: str) -> str:
    """The whole of a small sysfs file as ASCII text (bytes outside ASCII replaced), at the OS level:
    a buffered text stream costs more than the read itself, every 2 s per probe."""
    fd = os.open(path, os.O_RDONLY)
    try:
        chunks = []
        while chunk := os.read(fd, 4096):
            chunks.append(chunk)
            if len(chunk) < 4096:          # a short read of a regular or sysfs file is its end
                break
    finally:
        os.close(fd)
    return b"".join(chunks).decode("ascii", "replace")


class W1ProbeArray:
    """``ProbeArray`` over ``<w1_root>/28-<serial>/w1_slave``, in ``config.probes`` order."""

    def __init__(self, config: ProbeConfig) -> None:
        self.root = Path(config.w1_root)
        self.probes = {name: normalise_serial(serial, f"probes.{name}") for name, serial in config.probes.items()}
        self.fault_counts: dict[str, Counter[str]] = {name: Counter() for name in self.probes}
        self.good_reads: Counter[str] = Counter()
        self._paths: dict[str, str] = {}         # w1_slave path per probe (read every 2 s of bench time)
        # per probe: the last text read and what it said (celsius, fault kind, detail): the file changes
        # only with a new conversion result, so the same text is not parsed and checked again
        self._last: dict[str, tuple[str, float | None, str | None, str]] = {}

    def path_of(self, name: str) -> Path:
        return self.root / f"{FAMILY_PREFIX}{self.probes[name]}" / "w1_slave"

    def read_one(self, name: str) -> ProbeReading:
        serial = self.probes[name]
        path = self._paths.get(name) or self._paths.setdefault(name, str(self.path_of(name)))
        try:
            text = _read_text(path)
        except OSError as exc:
            return self._reject(name, FAULT_VANISHED, f"{path}: {exc.strerror or exc}")
        last = self._last.get(name)
        if last is not None and last[0] == text:
            _, celsius, kind, detail = last
        else:
            try:
                celsius, kind, detail = classify(parse_w1_slave(text))
            except ProtocolError as exc:
                celsius, kind, detail = None, FAULT_MALFORMED, str(exc)
            self._last[name] = (text, celsius, kind, detail)
        if kind is not None:
            return self._reject(name, kind, f"{path}: {detail}")
        self.good_reads[name] += 1
        return ProbeReading(name, serial, celsius)

    def read_all(self) -> list[ProbeReading]:
        return [self.read_one(name) for name in self.probes]

    def fault_totals(self) -> Counter[str]:
        total: Counter[str] = Counter()
        for counts in self.fault_counts.values():
            total.update(counts)
        return total

    def _reject(self, name: str, kind: str, detail: str) -> ProbeReading:
        self.fault_counts[name][kind] += 1
        return ProbeReading(name, self.probes[name], None, f"{kind}: {detail}")

"""Simulated Linux w1 sysfs tree for DS18B20 probes: ``<root>/28-<serial>/w1_slave`` (+ ``temperature``).

Byte for byte the kernel ``w1_therm`` format (reference section 4.2, see
``bench.devices.ds18b20`` for the layout): line 1 = the 9 scratchpad bytes just read + the
computed Dallas CRC-8 of bytes 0..7 + YES/NO; line 2 = the last good (CRC-valid) bytes +
``t=`` millidegrees from the *current* read, C truncating division (0xFFFF -> -62, not -63).
A fresh tree retains nine zero bytes until the first good read (the kernel zero-initialises).

Scratchpad of a good conversion: temperature rounded to 0.0625 C (12 bit; at 9..11 bit the
undefined low bits are zero), clamped to the sensor's -55..+125 C; TH 0x4B, TL 0x46; config
0x1F/0x3F/0x5F/0x7F for 9..12 bit; 0xFF; byte 6 = 0x10 - (raw & 0x0F), as genuine parts show
(``72 01 ... 0e 10`` for 0x0172 in the reference; 0x0C is then only seen at power-up); 0x10; CRC.

``temperature`` holds ``t`` in millidegrees followed by a newline.  The kernel answers -EIO on a
CRC failure; a regular file cannot, so while a CRC fault is active the file is removed (a
reader gets an ``OSError`` either way).

Timing: the probes' temperatures come from ``source.probe_temperatures()`` (position name -> C)
after ``source.advance_to(clock.now())``.  Files are rewritten at most once per
``conversion_s`` of bench time (750 ms at 12 bit) and no faster than ``min_wall_interval_s``
(20 ms) of wall time; each file is written to a temporary name and ``os.replace``-d, so a reader
never sees half a file.

On a lockstep clock (``bench.clock.LockstepClock``) there is no refresh thread: the clock calls
``serve(t)`` at each bench instant and the files are rewritten then (once per ``conversion_s``), so a
reader at bench time t sees the conversion finished at or just before t whatever the host load.

Faults (``sim.faults``, a ``W1Faults``): ``set(name, kind, duration_s=None)`` with kind one of

- ``"crc"``: bus open: line 1 ``ff`` x 9 ``crc=c9 NO``, line 2 last good bytes ``t=-62``;
- ``"power_on_85"``: ``50 05 4b 46 7f ff 0c 10 1c`` ``crc=1c YES``, ``t=85000``;
- ``"all_zero"``: ``00`` x 9 ``crc=00 YES``, ``t=0`` (passes the CRC);
- ``"failed_conversion"``: register 0x07FF with byte 6 = 0x0C, ``t=127937``;
- ``"vanished"``: the ``28-<serial>`` directory is removed; it comes back when the fault ends.

``duration_s`` is bench seconds (``None`` = until ``clear(name)``).
"""
from __future__ import annotations

import logging
import os
import shutil
import threading
from pathlib import Path
from typing import Protocol

from bench.background import BackgroundLoop
from bench.clock import Clock
from bench.devices.ds18b20 import (FAULT_ALL_ZERO, FAULT_CRC, FAULT_FAILED_CONVERSION, FAULT_POWER_ON,
                                   FAULT_VANISHED, FAMILY_PREFIX, MAX_C, MIN_C, dallas_crc8, millidegrees,
                                   normalise_serial, raw_temperature)

SIM_FAULT_KINDS = (FAULT_CRC, FAULT_POWER_ON, FAULT_ALL_ZERO, FAULT_FAILED_CONVERSION, FAULT_VANISHED)
TH, TL = 0x4B, 0x46
log = logging.getLogger(__name__)


class ProbeSource(Protocol):
    def advance_to(self, t: float) -> None: ...
    def probe_temperatures(self) -> dict[str, float]: ...


def config_byte(bits: int) -> int:
    if not 9 <= bits <= 12:
        raise ValueError(f"DS18B20 resolution must be 9..12 bits, got {bits}")
    return 0x1F | ((bits - 9) << 5)


def with_crc(first8: bytes) -> bytes:
    return first8 + bytes([dallas_crc8(first8)])


def good_scratchpad(celsius: float, bits: int = 12) -> bytes:
    """Scratchpad of a successful conversion of ``celsius`` at ``bits`` resolution."""
    raw = round(min(max(celsius, MIN_C), MAX_C) * 16)
    undefined = 12 - bits
    raw = (raw >> undefined) << undefined
    key = (raw, bits)
    pad = _GOOD.get(key)
    if pad is None:             # at most one per register value (a few thousand): every probe, every 2 s
        reg = raw & 0xFFFF
        pad = _GOOD[key] = with_crc(bytes([reg & 0xFF, reg >> 8, TH, TL, config_byte(bits), 0xFF,
                                           0x10 - (raw & 0x0F), 0x10]))
    return pad


_GOOD: dict[tuple[int, int], bytes] = {}


POWER_ON_SCRATCHPAD = with_crc(bytes([0x50, 0x05, TH, TL, 0x7F, 0xFF, 0x0C, 0x10]))
FAILED_CONVERSION_SCRATCHPAD = with_crc(bytes([0xFF, 0x07, TH, TL, 0x7F, 0xFF, 0x0C, 0x10]))
BUS_OPEN_SCRATCHPAD = b"\xff" * 9
ALL_ZERO_SCRATCHPAD = bytes(9)
_FAULT_SCRATCHPADS = {FAULT_CRC: BUS_OPEN_SCRATCHPAD, FAULT_POWER_ON: POWER_ON_SCRATCHPAD,
                      FAULT_ALL_ZERO: ALL_ZERO_SCRATCHPAD, FAULT_FAILED_CONVERSION: FAILED_CONVERSION_SCRATCHPAD}


def w1_slave_text(current: bytes, retained: bytes) -> tuple[str, bool]:
    """Kernel ``w1_slave`` text for a read of ``current`` given the last good ``retained`` bytes.

    Returns (text, crc_ok).  When crc_ok the kernel retains ``current``; line 2 shows it.
    """
    crc = dallas_crc8(current[:8])
    ok = crc == current[8]
    shown = current if ok else retained
    line1 = "".join(f"{b:02x} " for b in current) + f": crc={crc:02x} {'YES' if ok else 'NO'}\n"
    line2 = "".join(f"{b:02x} " for b in shown) + f"t={millidegrees(raw_temperature(current))}\n"
    return line1 + line2, ok


class W1Faults:
    def __init__(self, clock: Clock) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._active: dict[str, tuple[str, float | None]] = {}

    def set(self, name: str, kind: str, duration_s: float | None = None) -> None:
        if kind not in SIM_FAULT_KINDS:
            raise ValueError(f"unknown DS18B20 fault {kind!r}; expected one of {SIM_FAULT_KINDS}")
        until = None if duration_s is None else self._clock.now() + duration_s
        with self._lock:
            self._active[name] = (kind, until)

    def clear(self, name: str) -> None:
        with self._lock:
            self._active.pop(name, None)

    def active(self, name: str) -> str | None:
        if not self._active:         # no fault set (the usual case): no lock to take
            return None
        with self._lock:
            entry = self._active.get(name)
            if entry is None:
                return None
            kind, until = entry
            if until is not None and self._clock.now() >= until:
                del self._active[name]
                return None
            return kind


class W1TreeSimulator(BackgroundLoop):
    thread_name = "w1-sim"

    def __init__(self, source: ProbeSource, clock: Clock, root: str | Path, probes: dict[str, str],
                 conversion_s: float = 0.75, *, resolution_bits: int = 12,
                 min_wall_interval_s: float = 0.02) -> None:
        if conversion_s <= 0:
            raise ValueError(f"conversion_s must be > 0, got {conversion_s}")
        config_byte(resolution_bits)
        super().__init__()
        self.source = source
        self.clock = clock
        self.root = Path(root)
        self.probes = {name: normalise_serial(serial, f"probes.{name}") for name, serial in probes.items()}
        self.conversion_s = conversion_s
        self.resolution_bits = resolution_bits
        self.min_wall_interval_s = min_wall_interval_s
        self.faults = W1Faults(clock)
        self.updates = 0
        self.error: Exception | None = None      # set if the simulator thread died
        self.last_update_t: float | None = None
        self._retained = {name: bytes(9) for name in self.probes}
        self._written: dict[str, str] = {}          # last w1_slave text written per probe
        self._last_read: dict[str, tuple[bytes, bytes]] = {}   # (scratchpad, retained) behind that text
        self._lock = threading.Lock()
        self._dirs: dict[str, str] = {}              # device directory per probe (checked every instant)
        self._root_key: tuple[int, int, int] | None = None   # the root's inode, links, mtime when listed
        self._listing: set[str] = set()

    def device_dir(self, name: str) -> Path:
        return self.root / f"{FAMILY_PREFIX}{self.probes[name]}"

    def _device_dir_str(self, name: str) -> str:
        cached = self._dirs.get(name)
        if cached is None:
            cached = self._dirs[name] = str(self.device_dir(name))
        return cached

    def _before_start(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        self.update()

    def start(self) -> None:
        if getattr(self.clock, "lockstep", False):    # the clock calls serve() at each bench instant
            self._before_start()
            return
        super().start()

    def serve(self, t: float) -> None:
        """Lockstep: a new conversion when ``conversion_s`` has passed since the last one."""
        if self.last_update_t is None or t - self.last_update_t >= self.conversion_s - 1e-9:
            self.update()

    def _run(self) -> None:
        try:
            while not self._stop.wait(self.min_wall_interval_s):
                if self.last_update_t is None or self.clock.now() - self.last_update_t >= self.conversion_s:
                    self.update()
        except Exception as exc:  # noqa: BLE001 - a dead simulator must say why
            self.error = exc
            log.exception("w1 tree simulator stopped")

    def update(self) -> None:
        """One conversion of every probe at the current bench time; rewrite all files."""
        with self._lock:
            now = self.clock.now()
            self.source.advance_to(now)
            temps = self.source.probe_temperatures()
            present = self._present()
            for name in self.probes:
                if name not in temps and self.faults.active(name) is None:
                    raise KeyError(f"probe source has no temperature for position {name!r} "
                                   f"(has {sorted(temps)})")
                self._write_probe(name, temps.get(name), present)
            self.updates += 1
            self.last_update_t = now

    def _present(self) -> set[str] | None:
        """The names of the device directories in the tree now (None when the root itself is gone): a
        directory taken away from outside is written again at the next conversion.  Listed again only when
        the root changed (its link count and modification time move with every directory added or removed):
        one ``stat`` per conversion for every probe."""
        try:
            st = os.stat(self.root)
            key = (st.st_ino, st.st_nlink, st.st_mtime_ns)
            if key != self._root_key:
                self._listing = set(os.listdir(self.root))
                self._root_key = key
        except FileNotFoundError:
            self._root_key = None
            return None
        return self._listing

    def _write_probe(self, name: str, celsius: float | None, present: set[str] | None) -> None:
        fault = self.faults.active(name)
        if fault == FAULT_VANISHED:
            directory = self.device_dir(name)
            shutil.rmtree(directory, ignore_errors=True)
            self._written.pop(name, None)
            self._last_read.pop(name, None)
            return
        current = None if fault is None else _FAULT_SCRATCHPADS[fault]
        if current is None:
            current = good_scratchpad(celsius, self.resolution_bits)
        read = (current, self._retained[name])
        here = present is not None and FAMILY_PREFIX + self.probes[name] in present
        if here and self._last_read.get(name) == read and name in self._written:
            return              # the same conversion result as the files already show
        directory = self._device_dir_str(name)
        text, ok = w1_slave_text(current, self._retained[name])
        if ok:
            self._retained[name] = current
        present = here and os.path.isdir(directory)
        if self._written.get(name) == text and present:
            self._last_read[name] = read
            return              # same conversion result: the files already say exactly this
        if not present:
            os.makedirs(directory, exist_ok=True)
        _atomic_write(os.path.join(directory, "w1_slave"), text)
        temperature_file = os.path.join(directory, "temperature")
        if ok:
            _atomic_write(temperature_file, f"{millidegrees(raw_temperature(current))}\n")
        else:
            try:
                os.unlink(temperature_file)
            except FileNotFoundError:
                pass
        self._written[name] = text
        self._last_read[name] = read


def _atomic_write(path: str, text: str) -> None:
    head, name = os.path.split(path)
    tmp = os.path.join(head, f".{name}.tmp{os.getpid()}.{threading.get_ident()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
    try:
        os.write(fd, text.encode("ascii"))
    finally:
        os.close(fd)
    os.replace(tmp, path)

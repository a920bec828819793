"""Driver for an Acutronic ACUTROL3000 two-axis table ("ACL" command language).

Protocol facts (reference/device-protocols.md section 2.1; Acutronic TM-8004 rev C, TM-9384C
TCP/IP, TM-9411 RS-232 bridge at 9600 8N1): SCPI-like headers, one space before the arguments,
commas between them, ``;`` chaining; commands end with ``\\r\\n``; on serial/TCP *every* command
gets a reply (``OK`` for settings, data for queries, an error otherwise).

Commands used: ``:Mode:Position|Rate|Off <ax>``, ``:Mode? <ax>``, ``:Demand:Position <ax>,<deg>``,
``:Demand:Rate <ax>,<dps>``, ``:Demand:Acceleration <ax>,<dps2>``, ``:Read:Position? <ax>``,
``:Read:Rate? <ax>`` (chained as ``:Read:Position? 1;Rate? 1`` -> ``10.0001;44.1250``),
``:Limit:Rate <mode>,<ax>,<dps>``, ``:Interlock:Close|Open <ax>``, ``:Interlock? <ax>``,
``:Interlock:Reset``, ``*IDN?``.

Reply framing (``TurntableConfig.framing``):

- ``"line"`` (default): one reply line per command line; ``OK``, data, or ``ERR <code>,<message>``.
- ``"acutrol_header"``: 8-byte prefix then data.  ASSUMED layout (the manual says only "error code
  and message length prefixed to the data"; a public driver strips 8 bytes): int32 little-endian
  error code (0 = OK) + uint32 little-endian data length, then that many bytes of ASCII (``OK``,
  query data or the error message), no terminator.  Check against the real controller before use.

A refused command raises ``TurntableCommandError`` (a ``DeviceError``) with the controller's code.
Link/timeouts follow ``bench.devices.serial_line``.  Requests are idempotent (absolute demands),
so a broken link is reconnected and the request repeated once.
"""
from __future__ import annotations

import math
import re
import struct
import time
from collections.abc import Callable, Sequence

from bench.clock import Clock, Deadline, RealClock
from bench.config import TurntableConfig
from bench.devices.serial_line import SerialLine
from bench.errors import BenchError, DeviceError, DeviceTimeout, ProtocolError
from bench.interfaces import AxisState

_ERR_LINE = re.compile(r"ERR\s*(-?\d+)\s*,\s*(.*)", re.DOTALL)
_NUMBER = re.compile(r"-?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_HEADER = struct.Struct("<iI")
MAX_REPLY_BYTES = 4096
MODE_NAMES = {"P": "position", "R": "rate", "O": "off"}


class TurntableCommandError(DeviceError):
    """The controller answered a command with an error."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class InvalidAxis(BenchError, ValueError):
    """An axis number outside 1..axes."""


class AcutrolTurntable:
    """``Turntable`` implementation.  ``clock`` is used only to wait for moves (bench time).

    ``poll_s``: bench seconds between position polls while waiting.  Each wait is bounded by a
    bench-time deadline (travel estimate x2 + 10 s unless given) and a wall-time deadline (the
    bench deadline converted with ``clock.speed`` + 10 s), whichever comes first.
    """

    def __init__(self, config: TurntableConfig, clock: Clock | None = None, *, poll_s: float = 0.05,
                 settle_rate_dps: float = 0.001) -> None:
        self.config = config
        self.axes = config.axes
        self.clock = clock or RealClock()
        self.poll_s = poll_s
        self.settle_rate_dps = settle_rate_dps
        self.line = SerialLine(config.url, baudrate=config.baudrate, timeout_s=config.timeout_s,
                               name="turntable", write_terminator=b"\r\n", read_terminator=b"\n")
        self._configured: set[int] = set()
        self._rate_limit = {a: config.rate_limit_dps for a in range(1, self.axes + 1)}
        self._accel = {a: config.acceleration_dps2 for a in range(1, self.axes + 1)}

    def guard_requests(self, guard: Callable[[], None] | None) -> None:
        """Call ``guard`` before every request put on the line (it raises to keep one off)."""
        self.line.request_guard = guard

    # low level -----------------------------------------------------------------------------------
    def command(self, text: str) -> None:
        """Send a non-query command line; the controller must answer ``OK``."""
        reply = self._transact(text)
        if reply != "OK":
            raise ProtocolError(f"turntable at {self.config.url}: expected 'OK' after {text!r}, got {reply!r}")

    def query(self, text: str) -> str:
        return self._transact(text)

    def _transact(self, text: str) -> str:
        if self.config.framing == "line":
            code, data = self.line.transact(text, lambda ln: self._read_line_reply(ln, text))
        else:
            code, data = self.line.transact(text, lambda ln: self._read_header_reply(ln, text))
        if code != 0:
            raise TurntableCommandError(f"turntable at {self.config.url} refused {text!r}: {code},{data}", code)
        return data

    @staticmethod
    def _read_line_reply(line: SerialLine, request: str) -> tuple[int, str]:
        text = line.read_line(request).strip()
        match = _ERR_LINE.fullmatch(text)
        if match:
            return int(match.group(1)), match.group(2)
        if text.upper().startswith("ERR"):
            raise ProtocolError(f"turntable at {line.url}: malformed error reply to {request!r}: {text!r}")
        return 0, text

    @staticmethod
    def _read_header_reply(line: SerialLine, request: str) -> tuple[int, str]:
        code, length = _HEADER.unpack(line.read_exact(_HEADER.size, request))
        if length > MAX_REPLY_BYTES:
            raise ProtocolError(f"turntable at {line.url}: reply header to {request!r} announces {length} "
                                f"bytes (max {MAX_REPLY_BYTES}); framing lost")
        data = line.read_exact(length, request) if length else b""
        return code, line.decode(data, request)

    def _number(self, text: str, what: str) -> float:
        if not _NUMBER.fullmatch(text.strip()):
            raise ProtocolError(f"turntable at {self.config.url}: {what}: expected a number, got {text!r}")
        return float(text)

    def _axis(self, axis: int) -> int:
        if not isinstance(axis, int) or isinstance(axis, bool) or not 1 <= axis <= self.axes:
            raise InvalidAxis(f"turntable: axis {axis!r} not in 1..{self.axes}")
        return axis

    @staticmethod
    def _value(value: float, what: str) -> str:
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"turntable: {what} must be a finite number, got {value!r}")
        return repr(float(value))

    # Turntable protocol ----------------------------------------------------------------------------
    def identify(self) -> str:
        return self.query("*IDN?")

    def interlock_close(self, axis: int) -> None:
        self.command(f":Interlock:Close {self._axis(axis)}")

    def interlock_open(self, axis: int) -> None:
        self.command(f":Interlock:Open {self._axis(axis)}")

    def interlock_reset(self) -> None:
        self.command(":Interlock:Reset")

    def interlock_state(self, axis: int) -> str:
        """``Closed``, ``Open`` or ``Fault`` (as the controller spells it)."""
        return self.query(f":Interlock? {self._axis(axis)}")

    def mode(self, axis: int) -> str:
        """``position``, ``rate`` or ``off`` (accepts ``P``/``Position``-style replies)."""
        reply = self.query(f":Mode? {self._axis(axis)}").strip()
        key = reply[:1].upper()
        if key not in MODE_NAMES:
            raise ProtocolError(f"turntable at {self.config.url}: unknown mode reply {reply!r}")
        return MODE_NAMES[key]

    def set_acceleration(self, axis: int, dps2: float) -> None:
        self.command(f":Demand:Acceleration {self._axis(axis)},{self._value(dps2, 'acceleration')}")
        self._accel[axis] = float(dps2)

    def set_rate_limit(self, axis: int, dps: float, mode: str = "P") -> None:
        if mode.upper() not in ("P", "R"):
            raise ValueError(f"turntable: rate-limit mode must be 'P' or 'R', got {mode!r}")
        self.command(f":Limit:Rate {mode.upper()},{self._axis(axis)},{self._value(dps, 'rate limit')}")
        if mode.upper() == "P":
            self._rate_limit[axis] = float(dps)

    def read(self, axis: int) -> AxisState:
        return self.read_axes([axis])[axis]

    def read_axes(self, axes: Sequence[int]) -> dict[int, AxisState]:
        """Position and rate of each of ``axes`` in one chained query (``:Read:Position? 1;Rate? 1;Position?
        2;Rate? 2`` -> ``10.0001;44.1250;0.0000;0.0000``): one round trip for the whole table."""
        numbers = [self._axis(a) for a in axes]
        reply = self.query(":Read:" + ";".join(f"Position? {a};Rate? {a}" for a in numbers))
        parts = reply.split(";")
        if len(parts) != 2 * len(numbers):
            expected = ";".join(f"position{a};rate{a}" for a in numbers) if len(numbers) > 1 else "position;rate"
            raise ProtocolError(f"turntable at {self.config.url}: expected '{expected}', got {reply!r}")
        return {a: AxisState(self._number(parts[2 * i], f"axis {a} position"),
                             self._number(parts[2 * i + 1], f"axis {a} rate")) for i, a in enumerate(numbers)}

    def _demand(self, axis: int, mode: str, value: float) -> int:
        """Put ``axis`` in ``mode`` ("Position" deg / "Rate" deg/s) with demand ``value``; the axis number."""
        a = self._axis(axis)
        text = self._value(value, mode.lower())
        self._ensure_configured(a)
        self.command(f":Mode:{mode} {a}")
        self.command(f":Demand:{mode} {a},{text}")
        return a

    def move_to(self, axis: int, position_deg: float, *, wait: bool = True,
                timeout_s: float | None = None) -> AxisState:
        """Position mode to ``position_deg``; by default wait until within tolerance and at rest."""
        a = self._demand(axis, "Position", position_deg)
        if not wait:
            return self.read(a)
        if timeout_s is None:
            timeout_s = 2.0 * self._travel_estimate_s(a, 180.0) + 10.0
        return self._wait(a, lambda st: abs(_wrap(st.position_deg - position_deg)) <= self.config.position_tolerance_deg
                          and abs(st.rate_dps) <= self.settle_rate_dps,
                          timeout_s, f"reach {position_deg} deg")

    def rate(self, axis: int, rate_dps: float, *, wait: bool = False, tolerance_dps: float = 0.01,
             timeout_s: float | None = None) -> AxisState | None:
        """Rate mode at ``rate_dps``; with ``wait`` block until the rate is reached."""
        a = self._demand(axis, "Rate", rate_dps)
        if not wait:
            return None
        if timeout_s is None:
            timeout_s = 2.0 * (abs(rate_dps) * 2 / self._accel[a]) + 10.0
        return self._wait(a, lambda st: abs(st.rate_dps - rate_dps) <= tolerance_dps, timeout_s,
                          f"reach {rate_dps} deg/s")

    def off(self, axis: int) -> None:
        self.command(f":Mode:Off {self._axis(axis)}")

    def close(self) -> None:
        self.line.close()

    # helpers ------------------------------------------------------------------------------------
    def _ensure_configured(self, axis: int) -> None:
        """First motion on an axis: push the configured acceleration and position-mode rate limit."""
        if axis in self._configured:
            return
        self.set_acceleration(axis, self.config.acceleration_dps2)
        self.set_rate_limit(axis, self.config.rate_limit_dps, "P")
        self._configured.add(axis)

    def _travel_estimate_s(self, axis: int, degrees: float) -> float:
        v, acc = self._rate_limit[axis], self._accel[axis]
        return degrees / v + v / acc

    def _wait(self, axis: int, done, timeout_s: float, what: str) -> AxisState:
        deadline = Deadline(self.clock, timeout_s)
        speed = getattr(self.clock, "speed", 1.0)
        wall_budget = (timeout_s / speed if math.isfinite(speed) and speed > 0 else 0.0) + 10.0
        wall_deadline = time.monotonic() + wall_budget
        while True:
            state = self.read(axis)
            if done(state):
                return state
            if deadline.passed() or time.monotonic() > wall_deadline:
                raise DeviceTimeout(f"turntable at {self.config.url}: axis {axis} did not {what} within "
                                    f"{timeout_s:.1f} bench s (last position {state.position_deg}, "
                                    f"rate {state.rate_dps})")
            self.clock.sleep(self.poll_s)


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0

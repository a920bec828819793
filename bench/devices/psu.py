"""Driver for the gyro's SCPI bench power supply (serial or ``socket://`` TCP).

SCPI behaviour relied on (IEEE 488.2 / SCPI-1999): only queries return a line; settings return
nothing, so after each setting the driver reads ``SYST:ERR?`` to learn whether it was accepted
(the instrument's error queue, ``<code>,"<text>"``, ``0,"No error"`` when empty).

Commands: ``*IDN?``, ``OUTP ON|OFF``, ``OUTP?``, ``VOLT <v>``, ``CURR <a>``, ``MEAS:VOLT?``,
``MEAS:CURR?``, ``SYST:ERR?``.  Lines end with ``\\n``.  Requests are idempotent, so a broken
link is reopened and the request repeated once (``bench.devices.serial_line``).
"""
from __future__ import annotations

import math
import re
import threading
from collections.abc import Callable, Sequence

from bench.config import PsuConfig
from bench.devices.serial_line import SerialLine
from bench.errors import DeviceError, DeviceTimeout, ProtocolError

_ERROR_REPLY = re.compile(r'([+-]?\d+)\s*,\s*"(.*)"')
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
MAX_ERRORS_DRAINED = 25


class PsuCommandError(DeviceError):
    """The supply reported errors in its SCPI error queue after a command."""

    def __init__(self, message: str, errors: list[tuple[int, str]]) -> None:
        super().__init__(message)
        self.errors = errors
        self.code = errors[0][0] if errors else 0


class ScpiPowerSupply:
    """``PowerSupply`` implementation."""

    def __init__(self, config: PsuConfig) -> None:
        self.config = config
        self.line = SerialLine(config.url, baudrate=config.baudrate, timeout_s=config.timeout_s,
                               name="power supply", write_terminator=b"\n", read_terminator=b"\n")
        self.channel_lock = threading.Lock()     # held by its channels' requests (``PsuChannel``)

    def guard_requests(self, guard: Callable[[], None] | None) -> None:
        """Call ``guard`` before every request put on the line (it raises to keep one off)."""
        self.line.request_guard = guard

    # low level -----------------------------------------------------------------------------------
    def write(self, command: str) -> None:
        """Send a setting and raise ``PsuCommandError`` if the error queue is not empty afterwards."""
        self.line.send(command)
        self.check_errors(command)

    def query(self, command: str) -> str:
        try:
            return self.line.query_line(command).strip()
        except DeviceTimeout:
            # A refused query produces no reply: ask the error queue why before giving up.
            errors = self._drain_errors()
            if errors:
                raise self._error(command, errors) from None
            raise

    def check_errors(self, after: str = "") -> None:
        errors = self._drain_errors()
        if errors:
            raise self._error(after, errors)

    def _drain_errors(self) -> list[tuple[int, str]]:
        errors: list[tuple[int, str]] = []
        for _ in range(MAX_ERRORS_DRAINED):
            reply = self.line.query_line("SYST:ERR?").strip()
            match = _ERROR_REPLY.fullmatch(reply)
            if not match:
                raise ProtocolError(f"power supply at {self.config.url}: bad SYST:ERR? reply {reply!r}")
            code = int(match.group(1))
            if code == 0:
                return errors
            errors.append((code, match.group(2)))
        raise ProtocolError(f"power supply at {self.config.url}: error queue did not empty after "
                            f"{MAX_ERRORS_DRAINED} reads: {errors[:3]}...")

    def _error(self, command: str, errors: list[tuple[int, str]]) -> PsuCommandError:
        listed = "; ".join(f'{code},"{text}"' for code, text in errors)
        return PsuCommandError(f"power supply at {self.config.url} refused {command!r}: {listed}", errors)

    def _float(self, command: str) -> float:
        reply = self.query(command)
        if not _NUMBER.fullmatch(reply):
            raise ProtocolError(f"power supply at {self.config.url}: {command!r} returned {reply!r}, not a number")
        return float(reply)

    @staticmethod
    def _value(value: float, what: str) -> str:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ValueError(f"power supply: {what} must be a finite number >= 0, got {value!r}")
        return f"{float(value):.4f}"

    # PowerSupply protocol --------------------------------------------------------------------------
    def identify(self) -> str:
        return self.query("*IDN?")

    def output(self, on: bool) -> None:
        self.write("OUTP ON" if on else "OUTP OFF")

    def output_state(self) -> bool:
        reply = self.query("OUTP?").upper()
        if reply in ("1", "ON"):
            return True
        if reply in ("0", "OFF"):
            return False
        raise ProtocolError(f"power supply at {self.config.url}: OUTP? returned {reply!r}")

    def set_voltage(self, volts: float) -> None:
        self.write(f"VOLT {self._value(volts, 'voltage')}")

    def set_current_limit(self, amps: float) -> None:
        self.write(f"CURR {self._value(amps, 'current limit')}")

    def measure_voltage(self) -> float:
        return self._float("MEAS:VOLT?")

    def measure_current(self) -> float:
        return self._float("MEAS:CURR?")

    def reading(self) -> tuple[float, float, bool]:
        """(volts, amps, output on) in one program message, ``MEAS:VOLT?;:MEAS:CURR?;:OUTP?``: one round
        trip instead of three (the reply is the three results joined by ``;``)."""
        reply = self.query("MEAS:VOLT?;:MEAS:CURR?;:OUTP?")
        parts = [p.strip() for p in reply.split(";")]
        if len(parts) != 3 or not all(_NUMBER.fullmatch(p) for p in parts[:2]) or parts[2].upper() not in ("0", "1", "ON", "OFF"):
            raise ProtocolError(f"power supply at {self.config.url}: MEAS:VOLT?;:MEAS:CURR?;:OUTP? returned {reply!r}")
        return float(parts[0]), float(parts[1]), parts[2].upper() in ("1", "ON")

    def channel_readings(self, channels: Sequence[int]) -> list[tuple[float, float, bool]]:
        """(volts, amps, output on) of each of ``channels`` of a multi-channel supply in one program
        message, ``INST:NSEL n;:INST:NSEL?;:MEAS:VOLT?;:MEAS:CURR?;:OUTP?`` per channel: one round trip
        for the whole supply instead of one per channel.  The echoed selection proves each group was
        answered for its own channel (a refused ``INST:NSEL`` would leave the previous one selected);
        anything else is a ``ProtocolError`` (read the channels one by one to learn which)."""
        if not channels:
            return []
        message = ";:".join(f"INST:NSEL {int(ch)};:INST:NSEL?;:MEAS:VOLT?;:MEAS:CURR?;:OUTP?" for ch in channels)
        with self.channel_lock:
            reply = self.query(message)
        parts = [p.strip() for p in reply.split(";")]
        if len(parts) != 4 * len(channels):
            raise ProtocolError(f"power supply at {self.config.url}: {len(parts)} answers to the readings of "
                                f"channels {list(channels)}, expected {4 * len(channels)}: {reply!r}")
        out = []
        for k, ch in enumerate(channels):
            sel, volts, amps, on = parts[4 * k:4 * k + 4]
            if (not _NUMBER.fullmatch(sel) or float(sel) != ch or not _NUMBER.fullmatch(volts)
                    or not _NUMBER.fullmatch(amps) or on.upper() not in ("0", "1", "ON", "OFF")):
                raise ProtocolError(f"power supply at {self.config.url}: channel {ch} reading "
                                    f"{';'.join(parts[4 * k:4 * k + 4])!r} in {reply!r}")
            out.append((float(volts), float(amps), on.upper() in ("1", "ON")))
        return out

    def apply_config(self) -> None:
        """Set the configured voltage and current limit (output state unchanged)."""
        self.set_current_limit(self.config.current_limit_a)
        self.set_voltage(self.config.voltage_v)

    def close(self) -> None:
        self.line.close()



class PsuChannel(ScpiPowerSupply):
    """One output channel of a multi-channel SCPI supply as a ``PowerSupply`` of its own.

    Every request selects the channel in the same program message (``INST:NSEL n;:OUTP ON``,
    ``INST:NSEL n;:MEAS:VOLT?``: SCPI-1999 INSTrument subsystem, as on Keysight E36300, Rigol DP800,
    R&S HMP; ``;:`` starts the next command at the root), so a selection is never separated from its
    command, and one line costs one round trip.  Channels of one supply share its ``SerialLine`` and a
    lock (the error queue is the instrument's, read right after each setting under the same lock)."""

    def __init__(self, supply: ScpiPowerSupply, channel: int, lock) -> None:
        if isinstance(channel, bool) or not isinstance(channel, int) or channel < 1:
            raise ValueError(f"power supply channel must be an integer >= 1, got {channel!r}")
        self.config = supply.config
        self.line = supply.line
        self.channel = channel
        self.lock = lock

    def write(self, command: str) -> None:
        with self.lock:
            super().write(f"INST:NSEL {self.channel};:{command}")

    def query(self, command: str) -> str:
        with self.lock:
            return super().query(f"INST:NSEL {self.channel};:{command}")

    def close(self) -> None:
        """The shared line is closed by the supply that owns it (``close_devices``)."""

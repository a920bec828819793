"""Typed errors.  Every message names what failed and where (device, address, register, line...)."""
from __future__ import annotations


class BenchError(Exception):
    """Base class of every error this package raises on purpose."""


class DeviceError(BenchError):
    """A device did not do what was asked."""


class DeviceTimeout(DeviceError):
    """No (complete) reply within the timeout."""


class LinkDown(DeviceError):
    """The transport is closed or could not be opened."""


class ProtocolError(DeviceError):
    """A reply that does not follow the protocol (bad CRC, bad framing, unexpected text)."""


class ModbusException(DeviceError):
    """The Modbus slave answered with an exception code."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class IllegalAddress(ModbusException):
    """Modbus exception 02: unknown or inactive register."""


class IllegalValue(ModbusException):
    """Modbus exception 03: value out of range."""


class SensorFault(DeviceError):
    """A sensor reading that must not be used (CRC NO, 85.000 power-on value, all zero...)."""


class PlanError(BenchError):
    """A procedure plan is invalid; raised before anything moves."""


class DataFormatError(BenchError):
    """A data file (measured-data CSV, scenario file, config) is malformed.  Names line and column."""

    def __init__(self, message: str, *, line: int | None = None, column: str | None = None,
                 source: str | None = None) -> None:
        where = []
        if source:
            where.append(str(source))
        if line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(f"{': '.join([', '.join(where)] if where else [])}{': ' if where else ''}{message}")
        self.line = line
        self.column = column
        self.source = source


class LeaseLost(BaseException):
    """This worker no longer owns the run (another worker took it over after this one stopped
    heartbeating).  A ``BaseException`` on purpose, like ``KeyboardInterrupt``: no ``except Exception``
    on the way out (the engine's failure path, the safe-state sequence, a monitor's retry) may catch it
    and touch the run or the hardware again; it ends the run loop and reaches the worker."""

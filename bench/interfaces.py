"""The small interfaces each device driver implements (and the engine depends on).

A driver talks to real hardware or to its simulator over the same transport; nothing here knows
which.  All methods are blocking with bounded (wall-time) timeouts and raise ``bench.errors``
types.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class ChamberStatus:
    pv_c: float              # chamber air temperature (register 100)
    setpoint_c: float        # static set point (register 300)
    ramp_setpoint_c: float | None   # current ramping set point during a profile (4122), else None
    mode: int                # register 200: 0/1 constant, 2 profile running, 3 profile held
    alarm: int               # register 102, 0 = none
    input_error: int         # register 101, 0 = none
    power_on: bool           # event 1 (register 2000)


@runtime_checkable
class Chamber(Protocol):
    def read_temperature(self) -> float: ...
    def read_setpoint(self) -> float: ...
    def set_setpoint(self, celsius: float) -> None: ...
    def ramp_to(self, target_c: float, rate_c_per_min: float) -> None: ...
    def hold(self) -> None: ...
    def resume(self) -> None: ...
    def stop(self) -> None: ...
    def set_power(self, on: bool) -> None: ...
    def status(self) -> ChamberStatus: ...
    def setpoint_limits(self) -> tuple[float, float]: ...
    def clear_alarm(self) -> None: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class AxisState:
    position_deg: float
    rate_dps: float


@runtime_checkable
class Turntable(Protocol):
    axes: int

    def identify(self) -> str: ...
    def interlock_close(self, axis: int) -> None: ...
    def interlock_open(self, axis: int) -> None: ...
    def interlock_reset(self) -> None: ...
    def move_to(self, axis: int, position_deg: float) -> None: ...
    def rate(self, axis: int, rate_dps: float) -> None: ...
    def off(self, axis: int) -> None: ...
    def set_acceleration(self, axis: int, dps2: float) -> None: ...
    def set_rate_limit(self, axis: int, dps: float, mode: str = "P") -> None: ...
    def read(self, axis: int) -> AxisState: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class GyroFrame:
    """One decoded gyro frame.  ``raw`` holds the exact bytes received (bit-exact storage)."""

    host_time: float                       # bench-clock time the frame was taken off the line
    sequence: int
    gyro: tuple[float, float, float]       # as output by the device (deg/s for KVH rate mode)
    accel: tuple[float, float, float]      # g
    status: int
    temperature_c: float
    raw: bytes
    freq_hz: tuple[float, float, float] | None = None   # HRG resonance frequencies, None for KVH A


@dataclass
class LinkStats:
    frames: int = 0
    bad_crc: int = 0
    resyncs: int = 0              # times garbage had to be skipped to find a header
    skipped_bytes: int = 0
    sequence_gaps: int = 0        # number of gap events
    missing_frames: int = 0       # frames inferred missing from sequence jumps
    invalid_status: int = 0       # frames whose status is not all-valid
    reconnects: int = 0
    link_gaps: list[tuple[float, float]] = field(default_factory=list)  # (from, to) bench time


@runtime_checkable
class GyroLink(Protocol):
    stats: LinkStats

    def start(self) -> None: ...
    def drain(self, max_frames: int | None = None) -> list[GyroFrame]: ...
    def stop(self) -> None: ...


@dataclass(frozen=True)
class ProbeReading:
    name: str                     # position name, e.g. "t1"
    serial: str                   # 12 hex digits
    celsius: float | None         # None when the reading was rejected
    fault: str | None = None      # why it was rejected


@runtime_checkable
class ProbeArray(Protocol):
    def read_all(self) -> list[ProbeReading]: ...


@runtime_checkable
class PowerSupply(Protocol):
    def identify(self) -> str: ...
    def output(self, on: bool) -> None: ...
    def set_voltage(self, volts: float) -> None: ...
    def set_current_limit(self, amps: float) -> None: ...
    def measure_voltage(self) -> float: ...
    def measure_current(self) -> float: ...
    def output_state(self) -> bool: ...
    def close(self) -> None: ...

"""Bench configuration: which device sits on which address.

The same file drives real hardware and the simulated bench; only addresses differ.  Loaded from
JSON (``BenchConfig.load``).  Unknown keys are refused so a typo never silently falls back to a
default.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from bench.errors import DataFormatError


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ChamberConfig(_Strict):
    transport: Literal["modbus_tcp", "modbus_rtu"] = "modbus_rtu"
    # modbus_tcp: "host:port"; modbus_rtu: a serial device ("/dev/ttyUSB0") or pyserial URL
    # ("socket://127.0.0.1:5021" for RTU over TCP).
    address: str = "/dev/ttyUSB0"
    unit_id: int = Field(1, ge=0, le=247)
    baudrate: int = 9600
    timeout_s: float = Field(1.0, gt=0)
    retries: int = Field(2, ge=0)
    inter_frame_delay_s: float = Field(0.03, ge=0)   # Watlow recommends ~30 ms between transactions
    ramp_mode: Literal["profile", "host"] = "profile"
    profile_number: int = Field(1, ge=1, le=40)
    max_ramp_c_per_min: float = Field(5.0, gt=0)
    setpoint_min_c: float = -70.0
    setpoint_max_c: float = 180.0


class TurntableGeometry(_Strict):
    """Two-axis table carrying the chamber.

    ``outer_axis`` / ``inner_axis`` are unit vectors in the level frame (E, N, U) when both angles
    are zero, for the outer axis, and in the outer-gimbal frame for the inner axis.
    ``mounting`` maps gyro body axes to the inner-gimbal frame at zero angles: three letters as in
    orientation codes but relative to the inner gimbal at rest (default: body x=E, y=N, z=U at 0,0).
    """

    outer_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)   # vertical azimuth axis
    # horizontal tilt axis, along North at rest: with the gyro mounted ENU at (0, 0) this reaches all
    # eight positions of S000 (their body y axis is always horizontal, so y must sit on the inner axis)
    inner_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    mounting: str = "ENU"
    outer_axis_number: int = 1
    inner_axis_number: int = 2


class TurntableConfig(_Strict):
    url: str = "/dev/ttyS0"                     # pyserial URL or device; "socket://host:9878" for TCP
    baudrate: int = 9600
    framing: Literal["line", "acutrol_header"] = "line"
    timeout_s: float = Field(2.0, gt=0)
    axes: int = 2
    rate_limit_dps: float = 100.0
    acceleration_dps2: float = 50.0
    position_tolerance_deg: float = 0.01
    geometry: TurntableGeometry = TurntableGeometry()


class GyroConfig(_Strict):
    url: str = "/dev/ttyUSB1"
    baudrate: int = 921600
    frame: Literal["kvh_a", "hrg"] = "kvh_a"
    data_rate_hz: float = Field(1000.0, gt=0, le=5000)
    output_units: Literal["deg/s", "rad/s"] = "deg/s"
    # degrees C per count of the frame's temperature field: 0.01 with =TEMPUNITS in 1/100 C, 1.0 for
    # older firmware that reports whole degrees
    temp_scale: float = Field(0.01, gt=0)
    reconnect_s: float = Field(0.5, gt=0)       # wall seconds between reconnect attempts
    channels: tuple[str, ...] = ("x", "y", "z")
    # channel -> the probe position name (a key of ``probes.probes``) glued at that channel's own
    # temperature (S000 eq 4 uses t_i for channel i); recorded with every run, exported as the CSV
    # line ``# channel_probes: x=t1,y=t2,z=t3``; fits use it as each channel's default probe
    channel_probes: dict[str, str] = Field(default_factory=dict)
    # measurement range, deg/s (KVH DSP-1750: +-490); imported rates beyond it are refused
    range_dps: float = Field(490.0, gt=0, le=1e6)


class ProbeConfig(_Strict):
    w1_root: str = "/sys/bus/w1/devices"
    # position name -> 12-hex-digit serial ("28-" prefix optional)
    probes: dict[str, str] = Field(default_factory=dict)
    resolution_bits: int = Field(12, ge=9, le=12)


class PsuConfig(_Strict):
    url: str = "/dev/ttyUSB2"
    baudrate: int = 9600
    timeout_s: float = Field(1.0, gt=0)
    voltage_v: float = Field(28.0, ge=0)
    current_limit_a: float = Field(1.5, ge=0)


class SafeStateConfig(_Strict):
    chamber: Literal["setpoint", "hold"] = "setpoint"
    chamber_setpoint_c: float = 25.0
    gyro_power: Literal["off", "on", "keep"] = "off"
    park_outer_deg: float = 0.0
    park_inner_deg: float = 0.0
    timeout_s: float = Field(30.0, gt=0)


class GyroLimits(_Strict):
    min_c: float = -45.0
    max_c: float = 70.0


class SuspendRule(_Strict):
    """An extra condition that suspends a run (``bench.engine.suspenders``): ``signal`` below
    ``below`` (a floor) or above ``above`` (a ceiling), exactly one of them; the run may resume once
    the value is back at ``resume_at`` (default: the threshold).  Signals: ``chamber_pv_c``,
    ``psu_volts``, ``psu_amps``, ``probe:<name>``."""

    signal: str = Field(pattern=r"^(chamber_pv_c|psu_volts|psu_amps|probe:.+)$")
    below: float | None = None
    above: float | None = None
    resume_at: float | None = None

    @model_validator(mode="after")
    def _check_threshold(self) -> "SuspendRule":
        if (self.below is None) == (self.above is None):
            raise ValueError(f"suspend rule on {self.signal}: give exactly one of below / above")
        if self.resume_at is not None:
            if self.below is not None and self.resume_at < self.below:
                raise ValueError(f"suspend rule on {self.signal}: resume_at {self.resume_at:g} is below "
                                 f"the floor {self.below:g}")
            if self.above is not None and self.resume_at > self.above:
                raise ValueError(f"suspend rule on {self.signal}: resume_at {self.resume_at:g} is above "
                                 f"the ceiling {self.above:g}")
        return self


class BenchConfig(_Strict):
    name: str = "bench1"
    latitude_deg: float = Field(45.75, ge=-90, le=90)
    chamber: ChamberConfig = ChamberConfig()
    turntable: TurntableConfig = TurntableConfig()
    gyro: GyroConfig = GyroConfig()
    probes: ProbeConfig = ProbeConfig()
    psu: PsuConfig = PsuConfig()
    safe_state: SafeStateConfig = SafeStateConfig()
    gyro_limits: GyroLimits = GyroLimits()
    suspend: list[SuspendRule] = Field(default_factory=list)   # added to the bench's own suspend conditions

    @model_validator(mode="after")
    def _check_channel_probes(self) -> "BenchConfig":
        for ch, probe in self.gyro.channel_probes.items():
            if ch not in self.gyro.channels:
                raise ValueError(f"gyro.channel_probes: unknown channel {ch!r} (gyro.channels: "
                                 f"{', '.join(self.gyro.channels)})")
            if probe not in self.probes.probes:
                raise ValueError(f"gyro.channel_probes.{ch}: {probe!r} is not a configured probe (probes.probes: "
                                 f"{', '.join(sorted(self.probes.probes)) or 'none'})")
        for k, rule in enumerate(self.suspend):
            name = rule.signal.removeprefix("probe:")
            if rule.signal.startswith("probe:") and self.probes.probes and name not in self.probes.probes:
                raise ValueError(f"suspend.{k}.signal: {name!r} is not a configured probe (probes.probes: "
                                 f"{', '.join(sorted(self.probes.probes))})")
        return self

    @classmethod
    def load(cls, path: str | Path) -> "BenchConfig":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise DataFormatError("bench config file not found", source=str(path)) from None
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"not valid JSON: {exc.msg}", line=exc.lineno, source=str(path)) from None
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            loc = ".".join(str(p) for p in first["loc"])
            msg = first["msg"].removeprefix("Value error, ")
            raise DataFormatError(msg, column=loc or None, source=str(path)) from None

    def dump(self, path: str | Path) -> None:
        tmp = Path(str(path) + ".tmp")
        tmp.write_text(self.model_dump_json(indent=2))
        tmp.replace(path)

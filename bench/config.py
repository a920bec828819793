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
    # bench seconds: the registers only this host (or the operator at the front panel) changes in constant
    # mode, 200 mode and 2000 event 1, are read again at least this often (and after every write)
    status_refresh_s: float = Field(60.0, ge=0)


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


class SlotPower(_Strict):
    """How one gyro slot is powered: a channel of the bench's multi-channel SCPI supply (``channel``:
    ``INST:NSEL n`` then ``OUTP`` / ``VOLT`` / ``MEAS``) or a supply of its own (``psu``)."""

    channel: int | None = Field(None, ge=1, le=64)
    psu: PsuConfig | None = None
    voltage_v: float | None = Field(None, ge=0)          # default: the supply's (bench ``psu``) setting
    current_limit_a: float | None = Field(None, ge=0)

    @model_validator(mode="after")
    def _one_source(self) -> "SlotPower":
        if (self.channel is None) == (self.psu is None):
            raise ValueError("give exactly one of channel (a channel of the bench supply) / psu (its own supply)")
        return self


class GyroSlot(_Strict):
    """One gyro position of a multi-gyro fixture: its line, its probes, its power and its mounting.

    ``mounting``: the gyro's body axes relative to the inner gimbal at rest, as
    ``TurntableGeometry.mounting``; every slot of one fixture must realise the procedure's positions,
    so the slots share the bench's mounting unless the fixture turns a unit on purpose (its segments
    are then labelled with the orientation *its* axes reach)."""

    slot: str = Field(pattern=r"^[A-Za-z0-9_-]{1,32}$")
    gyro: GyroConfig
    probes: ProbeConfig = ProbeConfig()
    power: SlotPower
    mounting: str | None = None                           # default: turntable.geometry.mounting


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


def _check_channel_map(gyro: GyroConfig, probes: ProbeConfig, where: str) -> None:
    for ch, probe in gyro.channel_probes.items():
        if ch not in gyro.channels:
            raise ValueError(f"{where}.channel_probes: unknown channel {ch!r} ({where}.channels: "
                             f"{', '.join(gyro.channels)})")
        if probe not in probes.probes:
            raise ValueError(f"{where}.channel_probes.{ch}: {probe!r} is not a configured probe (probes.probes: "
                             f"{', '.join(sorted(probes.probes)) or 'none'})")


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
    # several gyros in one chamber: one entry per slot (empty: the single gyro of ``gyro`` / ``probes``
    # / ``psu``).  ``psu`` is then the multi-channel supply the slots' ``power.channel`` select.
    gyros: list[GyroSlot] = Field(default_factory=list)
    # what a fault of one unit (its line, probes or supply) does: ``continue`` marks that unit and lets
    # the others go on; ``suspend`` suspends the whole run as a single-gyro fault does
    unit_faults: Literal["continue", "suspend"] = "continue"

    @model_validator(mode="after")
    def _check_channel_probes(self) -> "BenchConfig":
        _check_channel_map(self.gyro, self.probes, "gyro")
        owner: dict[tuple[str, str], str] = {}      # (what, value) -> the slot using it
        for k, slot in enumerate(self.gyros):
            _check_channel_map(slot.gyro, slot.probes, f"gyros.{k}.gyro")
            used = [("slot", slot.slot), ("gyro.url", slot.gyro.url),
                    *(("probe serial", serial) for serial in slot.probes.probes.values())]
            if slot.power.channel is not None:
                used.append(("power.channel", str(slot.power.channel)))
            for what, value in used:
                if (what, value) in owner:
                    raise ValueError(f"gyros.{k}: {what} {value!r} is already used by slot {owner[what, value]!r}")
                owner[what, value] = slot.slot
        for k, rule in enumerate(self.suspend):
            name = rule.signal.removeprefix("probe:")
            if rule.signal.startswith("probe:") and self.probes.probes and name not in self.probes.probes:
                raise ValueError(f"suspend.{k}.signal: {name!r} is not a configured probe (probes.probes: "
                                 f"{', '.join(sorted(self.probes.probes))})")
        return self

    @property
    def multi(self) -> bool:
        """True when the bench carries a list of gyro slots (``gyros``)."""
        return bool(self.gyros)

    def slot(self, name: str) -> GyroSlot:
        for slot in self.gyros:
            if slot.slot == name:
                return slot
        raise KeyError(f"no gyro slot {name!r} (slots: {', '.join(s.slot for s in self.gyros) or 'none'})")

    def assign_gyros(self, gyro_ids: list[str]) -> list[tuple[str, str]]:
        """(slot, gyro id) for the gyros a run names on this multi-gyro bench: ``SLOT=ID`` puts gyro ID in
        that slot, a plain ``ID`` takes the next free slot in fixture order."""
        if not self.gyros:
            raise ValueError("this bench carries one gyro (no gyros list in its config): name one gyro")
        if not gyro_ids:
            raise ValueError(f"name at least one gyro (slots: {', '.join(s.slot for s in self.gyros)})")
        placed: dict[str, str] = {}
        plain = []
        for item in gyro_ids:
            slot, sep, gyro = item.partition("=")
            if not sep:
                plain.append(item)
                continue
            self.slot(slot)     # KeyError naming the slots
            if slot in placed:
                raise ValueError(f"slot {slot!r} is given two gyros ({placed[slot]!r}, {gyro!r})")
            placed[slot] = gyro
        free = [s.slot for s in self.gyros if s.slot not in placed]
        if len(plain) > len(free):
            raise ValueError(f"{len(gyro_ids)} gyros named but the bench has {len(self.gyros)} slots "
                             f"({', '.join(s.slot for s in self.gyros)})")
        placed.update(zip(free, plain))
        ids = list(placed.values())
        for gyro in ids:
            if not gyro or ids.count(gyro) > 1:
                raise ValueError(f"gyro id {gyro!r} is empty or named twice")
        return [(s.slot, placed[s.slot]) for s in self.gyros if s.slot in placed]

    def slot_mounting(self, slot: GyroSlot) -> TurntableGeometry:
        """The table geometry as seen by ``slot``'s body axes (its own mounting, if any)."""
        geo = self.turntable.geometry
        return geo if slot.mounting in (None, geo.mounting) else geo.model_copy(update={"mounting": slot.mounting})

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

"""The bundle of device interfaces the engine drives (protocols from ``bench.interfaces``).

A multi-gyro bench (``BenchConfig.gyros``) adds ``units``: per fixture slot its gyro line, probes
and power (its own supply or a channel of a shared one).  ``Devices.fixture`` builds that bundle;
its ``gyro`` / ``probes`` / ``psu`` are then the whole fixture (``LinkBank``, ``ProbeBank``,
``PowerBank``: start every line, read every probe, switch every unit), which is what steps and the
safe state act on; the acquisition reads each unit on its own (``bench.engine.fixture``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, Iterable, Sequence

from bench.errors import DeviceError
from bench.interfaces import Chamber, GyroFrame, GyroLink, LinkStats, PowerSupply, ProbeArray, ProbeReading, Turntable


@dataclass
class UnitDevices:
    """One gyro slot of a fixture: its line, its probes, its power and the settings of that power.
    ``shared_power``: ``psu`` is a channel of a supply several slots share (its link is the bench's,
    not the unit's: ``bench.engine.fixture``)."""

    slot: str
    gyro: GyroLink
    probes: ProbeArray
    psu: PowerSupply
    voltage_v: float
    current_limit_a: float
    shared_power: bool = False


@dataclass
class Devices:
    chamber: Chamber
    turntable: Turntable
    gyro: GyroLink
    probes: ProbeArray
    psu: PowerSupply
    units: tuple[UnitDevices, ...] = ()
    shared: tuple[Any, ...] = field(default=())     # supplies several units' channels share (closed once)

    @classmethod
    def fixture(cls, chamber: Chamber, turntable: Turntable, units: Sequence[UnitDevices],
                shared: Iterable[Any] = ()) -> "Devices":
        units = tuple(units)
        if not units:
            raise ValueError("a fixture needs at least one gyro unit")
        return cls(chamber=chamber, turntable=turntable, gyro=LinkBank(units), probes=ProbeBank(units),
                   psu=PowerBank(units), units=units, shared=tuple(shared))

    @property
    def multi(self) -> bool:
        return bool(self.units)

    def only(self, slots: Iterable[str]) -> "Devices":
        """The fixture reduced to ``slots`` (the gyros under test), in fixture order."""
        wanted = set(slots)
        unknown = wanted - {u.slot for u in self.units}
        if unknown:
            raise ValueError(f"no gyro slot {', '.join(sorted(unknown))} on this bench "
                             f"(slots: {', '.join(u.slot for u in self.units) or 'none'})")
        return Devices.fixture(self.chamber, self.turntable, [u for u in self.units if u.slot in wanted],
                               self.shared)

    def drivers(self) -> list[Any]:
        """Every driver of the bundle (a fixture: the chamber, the table, each unit's own, the shared supplies)."""
        if not self.units:
            return [self.chamber, self.turntable, self.gyro, self.probes, self.psu]
        return [self.chamber, self.turntable, *(d for u in self.units for d in (u.gyro, u.probes, u.psu)),
                *self.shared]

    def wrapped(self, wrap: Callable[[Any], Any]) -> "Devices":
        """The same bundle with every driver passed through ``wrap`` (e.g. lease fencing)."""
        if not self.units:
            return Devices(**{f.name: wrap(getattr(self, f.name)) for f in fields(self)
                              if f.name not in ("units", "shared")})
        units = [UnitDevices(u.slot, wrap(u.gyro), wrap(u.probes), wrap(u.psu), u.voltage_v, u.current_limit_a,
                             u.shared_power) for u in self.units]
        return Devices.fixture(wrap(self.chamber), wrap(self.turntable), units, self.shared)


def apply_settings(unit: UnitDevices) -> None:
    """A unit's own configured voltage and current limit, on its supply."""
    unit.psu.set_voltage(unit.voltage_v)
    unit.psu.set_current_limit(unit.current_limit_a)


class LinkBank:
    """Every gyro line of a fixture as one ``GyroLink``: started and stopped together; ``drain``
    returns the frames of all lines (slot order); ``stats`` adds the lines' counters up."""

    def __init__(self, units: Sequence[UnitDevices]) -> None:
        self.units = tuple(units)

    @property
    def stats(self) -> LinkStats:
        total = LinkStats()
        for unit in self.units:
            s = unit.gyro.stats
            for name in ("frames", "bad_crc", "resyncs", "skipped_bytes", "sequence_gaps", "missing_frames",
                         "invalid_status", "reconnects"):
                setattr(total, name, getattr(total, name) + getattr(s, name))
            total.link_gaps.extend(s.link_gaps)
        return total

    def start(self) -> None:
        for unit in self.units:
            unit.gyro.start()

    def drain(self, max_frames: int | None = None) -> list[GyroFrame]:
        frames: list[GyroFrame] = []
        for unit in self.units:
            frames.extend(unit.gyro.drain(max_frames))
        return frames

    def stop(self) -> None:
        errors = []
        for unit in self.units:          # every line is stopped even if one fails
            try:
                unit.gyro.stop()
            except Exception as exc:  # noqa: BLE001 - reported after the others stopped
                errors.append(exc)
        if errors:
            raise errors[0]


class ProbeBank:
    """Every unit's probes as one ``ProbeArray``; names are ``<slot>/<probe>``."""

    def __init__(self, units: Sequence[UnitDevices]) -> None:
        self.units = tuple(units)

    def read_all(self) -> list[ProbeReading]:
        return [ProbeReading(f"{unit.slot}/{r.name}", r.serial, r.celsius, r.fault)
                for unit in self.units for r in unit.probes.read_all()]


class PowerBank:
    """Every unit's power as one ``PowerSupply``: ``output`` switches all of them, ``output_state`` is
    True only when all are on; ``set_voltage`` / ``set_current_limit`` set every unit; ``measure_voltage``
    is the lowest unit voltage and ``measure_current`` the fixture's total current.

    Every command reaches every unit even when one unit's supply fails.  With ``unit_failed`` set
    (the fixture acquisition sets it: a unit's power is that unit's own) a unit's ``DeviceError`` is
    handed to ``unit_failed(slot, what, error)`` and the bank goes on (``output_state`` then speaks
    for the units that answered); without it the first error is raised once all units were tried."""

    def __init__(self, units: Sequence[UnitDevices]) -> None:
        self.units = tuple(units)
        self.unit_failed: Callable[[str, str, DeviceError], None] | None = None
        self.commanded: bool | None = None      # the output state last commanded (None: never)

    def _each(self, what: str, action: Callable[[UnitDevices], Any]) -> list[Any]:
        """``action`` on every unit; the results of the units that answered."""
        results, errors = [], []
        for unit in self.units:
            try:
                results.append(action(unit))
            except DeviceError as exc:
                if self.unit_failed is None:
                    errors.append(exc)
                else:
                    self.unit_failed(unit.slot, what, exc)
        if errors:
            raise errors[0]
        return results

    def identify(self) -> str:
        return "; ".join(f"{u.slot}: {u.psu.identify()}" for u in self.units)

    def output(self, on: bool) -> None:
        self.commanded = on
        self._each(f"output {'on' if on else 'off'}", lambda unit: unit.psu.output(on))

    def output_state(self) -> bool:
        return all(self._each("output state", lambda unit: unit.psu.output_state()))

    def set_voltage(self, volts: float) -> None:
        self._each(f"voltage {volts:g} V", lambda unit: unit.psu.set_voltage(volts))

    def set_current_limit(self, amps: float) -> None:
        self._each(f"current limit {amps:g} A", lambda unit: unit.psu.set_current_limit(amps))

    def apply_unit_settings(self) -> None:
        """Each unit's own configured voltage and current limit."""
        self._each("voltage and current limit", apply_settings)

    def measure_voltage(self) -> float:
        return min(unit.psu.measure_voltage() for unit in self.units)

    def measure_current(self) -> float:
        return sum(unit.psu.measure_current() for unit in self.units)

    def close(self) -> None:
        for unit in self.units:
            unit.psu.close()

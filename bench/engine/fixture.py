"""Acquisition for several gyros in one chamber (``FixtureAcquisition``).

One ``Acquisition`` (``bench.engine.monitor``) per gyro unit reads that unit's line, probes and power
into the unit's own run (the child run of the multi-gyro run), on the same bench-time schedule as a
single gyro; the chamber and the table are read once per telemetry instant (each on its own period) and their readings go to
the parent run and to every unit's run (so each unit's run is complete on its own: export, fits,
gaps and sampling work on it unchanged).

Conditions: the chamber's and the table's suspend the whole run.  A unit's own (its line down, its
frames stopped, its probes lost or unreadable, its supply link, the config's probe / supply
thresholds) follow ``BenchConfig.unit_faults``: ``suspend`` suspends the whole run (reason prefixed
with the slot); ``continue`` marks the unit faulted from its last frame on (event ``unit_fault``),
leaves its probes out of stability checks, and lets the others go on.  When the unit's condition
clears (a line fault: once its frames come back, not merely when its power goes off), the outage is recorded as a gap of the unit's run (unless its link already recorded one);
still faulted when the run ends, the gap runs to the end and the unit's run ends ``failed``
("the run's outcome says so": the parent's final reason lists the failed units).

A unit's power is its own too: a command to its supply that fails (the power step, the unit's
settings at the start, the safe state: ``PowerBank.unit_failed``) is that unit's "power supply link
down" condition, under the policy above, instead of failing the whole step.  The unit's supply is
then due the commanded state: once a reading of it succeeds again, its voltage, current limit and the
output last commanded are sent again.  A unit whose supply missed a power-on is a line fault (only
its frames coming back end it).

A supply several units share (a multi-channel supply, each unit on a channel: ``UnitDevices.shared_power``)
is bench equipment like the chamber and the table: when it does not answer (its link down or no reply,
on a reading or a command), that is one condition of the bench, "power supply link down", which always
suspends the run, not a fault of each unit on it.  Its channels are read together on the table's
schedule, in one program message (``ScpiPowerSupply.channel_readings``); when that reply is not
understood they are read one by one, and after the first that does not answer the others are not asked
again in that round.
The units whose command it missed are due their commanded state as above (sent again once it answers),
and their frames stopping meanwhile is part of the bench's condition (reason prefixed with the slot)
until their frames come back.  A channel's own refusal (an SCPI error, a reply not understood) is still
that unit's.

For steps the fixture reads like one bench (``StepReadings``): probe names are ``<slot>/<probe>``
of the units not faulted.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from bench.config import BenchConfig, TurntableGeometry
from bench.devices.orientation import angles_for, code_at
from bench.engine.config import EngineConfig
from bench.engine.devices import Devices, PowerBank, UnitDevices, apply_settings
from bench.engine.monitor import Acquisition, TelemetrySchedule
from bench.engine.outcomes import RunOutcome
from bench.engine.store import PsuReading, RunStore
from bench.engine.suspenders import LinkDown as LinkDownSuspender
from bench.errors import DeviceError, DeviceTimeout, LinkDown
from bench.interfaces import ChamberStatus

LogFn = Callable[..., None]
UNIT_SOURCES = ("gyro", "probes", "psu")          # what a unit owns; chamber and table are the bench's
BENCH_SOURCES = ("chamber", "table")
LINE_KEYS = ("gyro_link", "gyro_frames")           # conditions of a unit's line (``bench.engine.suspenders``)


@dataclass
class Unit:
    slot: str
    run_id: str
    acq: Acquisition
    dev: UnitDevices
    power_due: bool = False           # its supply missed a command: send the commanded state again
    fault_since: float | None = None
    fault_reason: str | None = None
    link_gaps_at_fault: int = 0
    frames_at_fault: int = 0
    line_fault: bool = False          # the line or its frames failed: only new frames end the fault
    supply_wait: bool = False         # its shared supply missed a command: the bench's fault until frames come back
    frames_at_power: int = 0          # frames when its commanded power was sent again
    faults: list[dict[str, Any]] = field(default_factory=list)

    @property
    def faulted(self) -> bool:
        return self.fault_since is not None


class FixtureAcquisition:
    def __init__(self, devices: Devices, store: RunStore, run_id: str, unit_runs: dict[str, str],
                 config: BenchConfig, engine_config: EngineConfig, log: LogFn, now: float,
                 clock_now: Callable[[], float] | None = None) -> None:
        self.store = store
        self.clock_now = clock_now or (lambda: now)
        self.run_id = run_id
        self.config = config
        self.log = log
        self.policy = config.unit_faults
        # the bench itself: chamber and table only
        self.bench = Acquisition(devices, store, run_id, config, engine_config, log, now)
        for source in UNIT_SOURCES:
            self.bench.suspenders[source] = []
        if any(unit_dev.shared_power for unit_dev in devices.units):     # the shared supply's link is the bench's
            self.bench.suspenders["psu"] = [LinkDownSuspender("psu")]
        self.units: list[Unit] = []
        for unit_dev in devices.units:
            slot = config.slot(unit_dev.slot)
            unit_config = config.model_copy(update={"gyro": slot.gyro, "probes": slot.probes, "gyros": []})
            view = Devices(devices.chamber, devices.turntable, unit_dev.gyro, unit_dev.probes, unit_dev.psu)
            acq = Acquisition(view, store, unit_runs[unit_dev.slot], unit_config, engine_config, log, now)
            for source in BENCH_SOURCES:
                acq.suspenders[source] = []
            acq.telemetry.never()    # the chamber, table and supply are read once for all (``_read_telemetry``)
            set_format = getattr(store, "set_format", None)
            if set_format is not None:
                set_format(unit_runs[unit_dev.slot], slot.gyro.frame, slot.gyro.data_rate_hz)
            self.units.append(Unit(unit_dev.slot, unit_runs[unit_dev.slot], acq, unit_dev))
        # the supply the shared_power units' channels belong to, and each one's channel
        self.shared_supply = devices.shared[0] if len(devices.shared) == 1 else None
        self.channels = {u.slot: config.slot(u.slot).power.channel for u in self.units if u.dev.shared_power}
        self.power = devices.psu if isinstance(devices.psu, PowerBank) else None
        if self.power is not None:
            self.power.unit_failed = self._power_failed
        self.telemetry = TelemetrySchedule(engine_config, now)
        self.conditions: dict[str, str] = {}

    # ---- the engine's acquisition interface --------------------------------------------------
    def tick(self, now: float, powered_since: float | None) -> None:
        for unit in self.units:
            unit.acq.tick(now, powered_since)
        chamber, table_psu = self.telemetry.due(now)
        if chamber or table_psu:
            self._read_telemetry(now, chamber, table_psu)
        self._update_conditions(now)

    def next_due(self) -> float:
        return min([self.telemetry.next_due(), *(unit.acq.next_due() for unit in self.units)])

    def flush(self, now: float) -> None:
        for unit in self.units:
            unit.acq.flush(now)

    def final_reading(self, now: float) -> None:
        """The chamber, table and every unit's supply once more after the safe state (see
        ``Acquisition.final_reading``)."""
        self._read_telemetry(now, True, True)

    def _read_telemetry(self, now: float, chamber: bool, table_psu: bool) -> None:
        """The chamber (every ``telemetry_period_s``) and the table (every ``table_psu_period_s``) once,
        to the parent and every unit's run; each unit's supply on the table's schedule."""
        status = self.bench.read_chamber(now) if chamber else None
        table = self.bench.read_table(now) if table_psu else None
        self.bench.record_telemetry(now, status, table, None)
        shared = self._read_shared_supply(now) if table_psu and self.channels else {}
        for unit in self.units:
            psu = None
            if table_psu:
                psu = shared.get(unit.slot) if unit.dev.shared_power else unit.acq.read_psu(now)
            if psu is not None and unit.power_due:
                self._power_again(unit, now)
            if status is not None:
                unit.acq.status, unit.acq.status_t = status, now
            unit.acq.record_telemetry(now, status, table, psu)

    def _read_shared_supply(self, now: float) -> dict[str, PsuReading]:
        """The shared supply's channels, by slot (those read): in one message where the supply offers it."""
        units = [unit for unit in self.units if unit.slot in self.channels]
        together = getattr(self.shared_supply, "channel_readings", None)
        if together is not None:
            try:
                values = together([self.channels[unit.slot] for unit in units])
            except (LinkDown, DeviceTimeout) as exc:
                self.bench.link_failed("psu", exc, now)
                return {}
            except DeviceError:
                values = None              # not understood: one channel at a time tells which
            if values is not None:
                self.bench.link_ok("psu", now)
                out = {}
                for unit, (volts, amps, on) in zip(units, values):
                    out[unit.slot] = PsuReading(volts=volts, amps=amps, on=on)
                    unit.acq.psu_read(out[unit.slot], now)
                return out
        out = {}
        for unit in units:
            reading = self._read_shared(unit, now)
            if reading is not None:
                out[unit.slot] = reading
            elif "psu_link" in self.bench.conditions:
                break                      # the supply does not answer: not asked again this round
        return out

    def _read_shared(self, unit: Unit, now: float) -> PsuReading | None:
        """The unit's channel of the shared supply: not answering is the bench's condition."""
        try:
            reading = unit.acq.measure_psu()
        except (LinkDown, DeviceTimeout) as exc:
            self.bench.link_failed("psu", exc, now)
            return None
        except DeviceError as exc:             # the supply answered: this channel's own trouble
            self.bench.link_ok("psu", now)
            unit.acq.link_failed("psu", exc, now)
            return None
        self.bench.link_ok("psu", now)
        unit.acq.psu_read(reading, now)
        return reading

    # ---- conditions and unit faults -------------------------------------------------------------
    def _update_conditions(self, now: float) -> None:
        conditions = dict(self.bench.conditions)
        for unit in self.units:
            own = unit.acq.conditions
            if unit.supply_wait:
                if not unit.power_due and (unit.acq.frames_total > unit.frames_at_power or not self._powered()):
                    unit.supply_wait = False
                elif "gyro_frames" in own:     # no power for its frames: the shared supply's fault
                    conditions[f"{unit.slot}:gyro_frames"] = f"{unit.slot}: {own['gyro_frames']} (its shared supply)"
                    own = {key: text for key, text in own.items() if key != "gyro_frames"}
            if self.policy == "suspend":
                conditions.update({f"{unit.slot}:{key}": f"{unit.slot}: {text}" for key, text in own.items()})
            elif own and not unit.faulted:
                self._mark(unit, now, "; ".join(own.values()))
            elif unit.faulted and not own and (not unit.line_fault or unit.acq.frames_total > unit.frames_at_fault):
                self._recovered(unit, now)
            if unit.faulted and (any(key in LINE_KEYS for key in own) or (unit.power_due and self._powered())):
                unit.line_fault = True
        self.conditions = conditions

    def _mark(self, unit: Unit, now: float, reason: str) -> None:
        last = unit.acq.last_frames_t
        unit.fault_since = last if last is not None and last <= now else now
        unit.fault_reason = reason
        unit.link_gaps_at_fault = unit.acq.link_gaps_seen
        unit.frames_at_fault = unit.acq.frames_total
        unit.line_fault = False
        unit.faults.append({"t_from": unit.fault_since, "reason": reason})
        self.log("warning", "unit_fault", f"gyro unit {unit.slot} (run {unit.run_id}) marked faulted: {reason}; "
                 f"the other units go on", slot=unit.slot, unit_run=unit.run_id, t_from=unit.fault_since)

    def _recovered(self, unit: Unit, now: float) -> None:
        assert unit.fault_since is not None
        if unit.acq.link_gaps_seen == unit.link_gaps_at_fault:     # the link itself recorded no gap
            self.store.add_gap(unit.run_id, unit.fault_since, now, _gap_reason(unit.fault_reason))
        unit.faults[-1]["t_to"] = now
        self.log("info", "unit_recovered", f"gyro unit {unit.slot} back after {now - unit.fault_since:.0f} s",
                 slot=unit.slot, unit_run=unit.run_id)
        unit.fault_since = unit.fault_reason = None

    # ---- a unit's power -------------------------------------------------------------------------
    def _powered(self) -> bool:
        return self.power is not None and bool(self.power.commanded)

    def _power_failed(self, slot: str, what: str, error: DeviceError) -> None:
        """``PowerBank.unit_failed``: a command to the unit's supply failed."""
        unit, now = self._unit(slot), self.clock_now()
        unit.power_due = True
        if unit.dev.shared_power and isinstance(error, (LinkDown, DeviceTimeout)):
            unit.supply_wait = True
            if "psu_link" not in self.bench.conditions:
                self.log("warning", "power_failed", f"shared power supply: {what} for gyro unit {slot} failed: "
                         f"{error}; the run suspends until it answers", slot=slot, unit_run=unit.run_id)
            self.bench.link_failed("psu", error, now)
            return
        self.log("warning", "unit_power_failed", f"gyro unit {slot}: power supply {what} failed: {error}",
                 slot=slot, unit_run=unit.run_id)
        unit.acq.link_failed("psu", error, now)

    def _power_again(self, unit: Unit, now: float) -> None:
        """The unit's supply answers again: its settings and the output last commanded, sent again."""
        assert self.power is not None
        on = self.power.commanded
        try:
            apply_settings(unit.dev)
            if on is not None:
                unit.dev.psu.output(on)
        except DeviceError as exc:
            if unit.dev.shared_power and isinstance(exc, (LinkDown, DeviceTimeout)):
                self.bench.link_failed("psu", exc, now)
            else:
                unit.acq.link_failed("psu", exc, now)
            return
        unit.power_due = False
        unit.frames_at_power = unit.acq.frames_total
        state = "" if on is None else f", output {'on' if on else 'off'}"
        self.log("info", "unit_power_restored", f"gyro unit {unit.slot}: power supply answers again; "
                 f"{unit.dev.voltage_v:g} V / {unit.dev.current_limit_a:g} A limit{state} sent again",
                 slot=unit.slot, unit_run=unit.run_id)

    # ---- what steps read (``StepReadings``) ----------------------------------------------------
    @property
    def status(self) -> ChamberStatus | None:
        return self.bench.status

    @property
    def status_t(self) -> float | None:
        return self.bench.status_t

    @property
    def probe_reads(self) -> int:
        return sum(unit.acq.probe_reads for unit in self.units)

    @property
    def probe_names(self) -> list[str]:
        return [f"{unit.slot}/{name}" for unit in self.units if not unit.faulted for name in unit.acq.probe_names]

    def read_chamber(self, now: float) -> ChamberStatus | None:
        return self.bench.read_chamber(now)

    def latest_probes(self) -> dict[str, float | None]:
        return {f"{unit.slot}/{name}": value for unit in self.units if not unit.faulted
                for name, value in unit.acq.latest_probes().items()}

    def probe_rate_c_per_min(self, name: str, now: float, window_s: float) -> float | None:
        slot, _, probe = name.partition("/")
        return self._unit(slot).acq.probe_rate_c_per_min(probe, now, window_s)

    def _unit(self, slot: str) -> Unit:
        for unit in self.units:
            if unit.slot == slot:
                return unit
        raise KeyError(f"no gyro unit {slot!r} in this run")

    # ---- what the engine fans out to every unit's run --------------------------------------------
    def add_segment(self, index: int, kind: str, t_from: float, t_to: float, labels: dict[str, Any]) -> None:
        for unit in self.units:
            self.store.add_segment(unit.run_id, index, kind, t_from, t_to, self._labels_for(unit.slot, labels))

    def _labels_for(self, slot: str, labels: dict[str, Any]) -> dict[str, Any]:
        """A slot mounted differently from the bench sees the table's position as another orientation of
        its own axes: its segments carry that one (and the bench's as ``bench_position``)."""
        position = labels.get("position")
        geo = self.config.turntable.geometry
        own = self.config.slot_mounting(self.config.slot(slot))
        if not isinstance(position, str) or own is geo:
            return labels
        return {**labels, "position": slot_position(position, geo, own), "bench_position": position}

    def add_gap(self, t_from_by_unit: Callable[[str], float], t_to: float, reason: str) -> None:
        for unit in self.units:
            self.store.add_gap(unit.run_id, t_from_by_unit(unit.run_id), t_to, reason)

    def set_status(self, status: str, now: float, reason: str | None) -> None:
        """The run's status, mirrored on every unit's run (a final one per unit: see ``finish``)."""
        if status in tuple(RunOutcome):
            return
        for unit in self.units:
            self.store.set_run_status(unit.run_id, status, now, None)

    def finish(self, status: RunOutcome, now: float, reason: str | None) -> str | None:
        """The run ends with ``status``: every unit's run ends too (a unit still faulted: its gap to the
        end recorded, ``failed``).  Returns the run's final reason, naming the failed units."""
        failed, unpowered = [], []
        for unit in self.units:
            if unit.power_due and self.power is not None and self.power.commanded is not None:
                unpowered.append(f"{unit.slot}: its supply did not take the last command "
                                 f"(output {'on' if self.power.commanded else 'off'})")
            if unit.faulted:
                assert unit.fault_since is not None
                # no next frame will close this gap: its missing frames are the unit's rate over it
                rate = self.config.slot(unit.slot).gyro.data_rate_hz
                self.store.add_gap(unit.run_id, unit.fault_since, now, _gap_reason(unit.fault_reason),
                                   frames_missing=max(0, int(round((now - unit.fault_since) * rate)) - 1))
                unit.faults[-1]["t_to"] = now
                text = f"{unit.fault_reason} (from bench time {unit.fault_since:.0f} to the end of the run)"
                self.store.set_run_status(unit.run_id, RunOutcome.FAILED, now, text)
                failed.append(f"{unit.slot}: {text}")
            else:
                self.store.set_run_status(unit.run_id, status, now, reason)
        notes = [reason] if reason else []
        if failed:
            notes.append(f"{len(failed)} of {len(self.units)} gyro units failed: " + "; ".join(failed))
        notes += unpowered
        return "; ".join(notes) if notes else None

    # ---- checkpoint ------------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        return {unit.slot: {"fault_since": unit.fault_since, "fault_reason": unit.fault_reason,
                            "line_fault": unit.line_fault, "faults": unit.faults} for unit in self.units}

    def restore(self, state: dict[str, Any] | None) -> None:
        for unit in self.units:
            saved = (state or {}).get(unit.slot)
            if saved:
                unit.fault_since, unit.fault_reason = saved.get("fault_since"), saved.get("fault_reason")
                unit.line_fault = bool(saved.get("line_fault"))
                unit.frames_at_fault = unit.acq.frames_total
                unit.faults = list(saved.get("faults") or [])


def slot_position(position: str, bench: TurntableGeometry, own: TurntableGeometry) -> str | None:
    """The orientation code a unit mounted as ``own`` reaches when the table stands where the bench's
    mounting reaches ``position`` (None: not an orientation code within 1 degree)."""
    outer, inner = angles_for(position, bench)
    code, off_deg = code_at(outer, inner, own)
    return code if off_deg <= 1.0 else None


def _gap_reason(reason: str | None) -> str:
    return f"unit fault: {reason or 'unknown'}"[:64]

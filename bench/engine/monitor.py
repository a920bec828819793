"""Data acquisition and condition watching, run once per engine tick.

Every tick: drain the gyro link (non-blocking) into a buffer handed to the store in batches, and
record new link gaps from ``LinkStats.link_gaps``.  When due: read the DS18B20 probes, the chamber
status (every ``telemetry_period_s``) and the turntable / PSU telemetry (every ``table_psu_period_s``).  After each read, the suspenders watching that source
(``bench.engine.suspenders``: the bench's own and those of ``BenchConfig.suspend``) update the
*conditions* that suspend a run, each with a human-readable reason.  Nothing here commands hardware.
"""
from __future__ import annotations

import collections
import itertools
import math
from typing import Callable

import numpy as np

from bench.config import BenchConfig
from bench.engine.config import EngineConfig
from bench.engine.devices import Devices
from bench.engine.store import PsuReading, RunStore
from bench.engine.suspenders import SOURCES, ProbeLost, Suspender, bench_suspenders
from bench.errors import DeviceError
from bench.interfaces import AxisState, ChamberStatus, GyroFrame

LogFn = Callable[..., None]
HISTORY_S = 3600.0   # probe history kept for stability checks


class Acquisition:
    def __init__(self, devices: Devices, store: RunStore, run_id: str, config: BenchConfig,
                 engine_config: EngineConfig, log: LogFn, now: float) -> None:
        self.devices = devices
        self.store = store
        self.run_id = run_id
        self.config = config
        self.cfg = engine_config
        self.log = log
        self.buffer: list[GyroFrame] = []
        self.frames_total = 0
        self.last_flush = now
        self.next_probe = now
        self.telemetry = TelemetrySchedule(engine_config, now)
        self.link_gaps_seen = len(devices.gyro.stats.link_gaps)
        self.last_frames_t: float | None = None
        self.status: ChamberStatus | None = None
        self.status_t: float | None = None
        self.probe_names: list[str] = list(config.probes.probes)
        self.probe_hist: dict[str, collections.deque[tuple[float, float]]] = {}
        self.probe_bad: dict[str, int] = {}
        self.probe_fault: dict[str, str] = {}
        self.probe_read_failures = 0
        self.probe_reads = 0          # successful reads so far (lets checks skip unchanged data)
        self.powered_since: float | None = None
        self.psu: PsuReading | None = None
        self.link_errors: dict[str, str] = {}
        self.conditions: dict[str, str] = {}
        self.suspenders: dict[str, list[Suspender]] = {source: [] for source in SOURCES}
        for suspender in bench_suspenders(config, self.probe_names):
            self.suspenders[suspender.source].append(suspender)
        self.outer_axis = config.turntable.geometry.outer_axis_number
        self.inner_axis = config.turntable.geometry.inner_axis_number

    # ---- conditions -------------------------------------------------------------------------
    def _link(self, source: str, error: DeviceError | None) -> None:
        if error is None:
            self.link_errors.pop(source, None)
        else:
            self.link_errors[source] = str(error)

    def link_failed(self, source: str, error: DeviceError, now: float) -> None:
        """A command to ``source`` failed (not one of the reads here): its link is down as after a failed read."""
        self._link(source, error)
        self._watch(source, now)

    def _watch(self, source: str, now: float) -> None:
        """After a read of ``source``: its suspenders update the conditions."""
        for suspender in self.suspenders[source]:
            reason = suspender.check(self, now)
            if reason is None:
                self.conditions.pop(suspender.key, None)
            else:
                self.conditions[suspender.key] = reason

    # ---- per tick -----------------------------------------------------------------------------
    def tick(self, now: float, powered_since: float | None) -> None:
        self.powered_since = powered_since
        self.drain(now)
        if now >= self.next_probe:
            self.next_probe = _next_on_grid(self.next_probe, now, self.cfg.probe_period_s)
            self.read_probes(now)
        chamber, table_psu = self.telemetry.due(now)
        if chamber or table_psu:
            self.read_telemetry(now, chamber=chamber, table_psu=table_psu)
        if len(self.buffer) >= self.cfg.frame_batch or now - self.last_flush >= self.cfg.frame_flush_s:
            self.flush(now)

    def next_due(self) -> float:
        """Bench time of the next scheduled probe read or telemetry (the engine wakes for it)."""
        return min(self.next_probe, self.telemetry.next_due())

    def drain(self, now: float) -> None:
        link = self.devices.gyro
        try:
            frames = link.drain()
        except DeviceError as exc:
            self._link("gyro", exc)
            frames = []
        else:
            self._link("gyro", None)
        if frames:
            self.buffer.extend(frames)
            self.frames_total += len(frames)
            self.last_frames_t = now
            while len(self.buffer) >= self.cfg.frame_batch:
                self._write(self.buffer[:self.cfg.frame_batch])
                del self.buffer[:self.cfg.frame_batch]
        gaps = link.stats.link_gaps
        if len(gaps) > self.link_gaps_seen:
            for t_from, t_to in gaps[self.link_gaps_seen:]:
                self.store.add_gap(self.run_id, float(t_from), float(t_to), "gyro link gap")
            self.link_gaps_seen = len(gaps)
        self._watch("gyro", now)

    def _write(self, frames: list[GyroFrame]) -> None:
        if frames:
            self.store.add_frames(self.run_id, frames)

    def flush(self, now: float) -> None:
        self._write(self.buffer)
        self.buffer = []
        self.last_flush = now

    # ---- probes -------------------------------------------------------------------------------
    def read_probes(self, now: float) -> None:
        try:
            readings = self.devices.probes.read_all()
        except DeviceError as exc:
            self.probe_read_failures += 1
            self._link("probes", exc)
            self._watch("probes", now)
            return
        self.probe_read_failures = 0
        self.probe_reads += 1
        self._link("probes", None)
        self.store.add_probe_readings(self.run_id, now, readings)
        by_name = {r.name: r for r in readings}
        if not self.probe_names:
            self.probe_names = sorted(by_name)
            self.suspenders["probes"][1:1] = [ProbeLost(name) for name in self.probe_names]
        for name in self.probe_names:
            reading = by_name.get(name)
            if reading is None or reading.celsius is None:
                self.probe_bad[name] = self.probe_bad.get(name, 0) + 1
                self.probe_fault[name] = ("missing from the bus" if reading is None
                                          else (reading.fault or "reading rejected"))
                continue
            self.probe_bad[name] = 0
            hist = self.probe_hist.setdefault(name, collections.deque())
            hist.append((now, float(reading.celsius)))
            while hist and hist[0][0] < now - HISTORY_S:
                hist.popleft()
        self._watch("probes", now)

    def latest_probes(self) -> dict[str, float | None]:
        return {name: (self.probe_hist[name][-1][1] if self.probe_hist.get(name) else None)
                for name in self.probe_names}

    def probe_rate_c_per_min(self, name: str, now: float, window_s: float) -> float | None:
        """Least-squares slope of probe ``name`` over the last ``window_s``; None until the window
        is (90 %) covered."""
        hist = self.probe_hist.get(name)
        if not hist or hist[0][0] > now - 0.9 * window_s:
            return None
        start = now - window_s
        pts = list(itertools.takewhile(lambda p: p[0] >= start, reversed(hist)))
        if len(pts) < 3:
            return None
        arr = np.asarray(pts, dtype=float)
        t = arr[:, 0] - arr[:, 0].mean()
        slope = float(np.dot(t, arr[:, 1] - arr[:, 1].mean()) / np.dot(t, t))
        return slope * 60.0

    # ---- telemetry ----------------------------------------------------------------------------
    def read_chamber(self, now: float) -> ChamberStatus | None:
        try:
            status = self.devices.chamber.status()
        except DeviceError as exc:
            self._link("chamber", exc)
            self._watch("chamber", now)
            return None
        self._link("chamber", None)
        self.status, self.status_t = status, now
        self._watch("chamber", now)
        return status

    def read_telemetry(self, now: float, *, chamber: bool = True, table_psu: bool = True) -> None:
        """Chamber status, and the turntable's two axes and the PSU's V / I / output (each when asked:
        the chamber every ``telemetry_period_s``, table and PSU every ``table_psu_period_s``)."""
        status = self.read_chamber(now) if chamber else None
        table = self.read_table(now) if table_psu else None
        psu_reading = self.read_psu(now) if table_psu else None
        self.record_telemetry(now, status, table, psu_reading)

    def final_reading(self, now: float) -> None:
        """The chamber, table and supply once more after the safe state, so the run's latest telemetry
        is the state the bench was left in (supply off, table parked), not the last reading before it."""
        self.read_telemetry(now)

    def read_table(self, now: float) -> dict[int, AxisState] | None:
        table: dict[int, AxisState] | None = {}
        try:
            turntable = self.devices.turntable
            both = getattr(turntable, "read_axes", None)        # one round trip where the driver offers it
            if both is not None:
                table = both((self.outer_axis, self.inner_axis))
            else:
                for axis in (self.outer_axis, self.inner_axis):
                    table[axis] = turntable.read(axis)
        except DeviceError as exc:
            self._link("table", exc)
            table = None
        else:
            self._link("table", None)
        self._watch("table", now)
        return table

    def read_psu(self, now: float) -> PsuReading | None:
        try:
            psu_reading = self.measure_psu()
        except DeviceError as exc:
            self.link_failed("psu", exc, now)
            return None
        self.psu_read(psu_reading, now)
        return psu_reading

    def measure_psu(self) -> PsuReading:
        """The supply's V / I / output now (``DeviceError`` when it does not answer); nothing recorded."""
        psu = self.devices.psu
        combined = getattr(psu, "reading", None)      # one round trip where the driver offers it
        if combined is not None:
            volts, amps, on = combined()
            return PsuReading(volts=volts, amps=amps, on=on)
        return PsuReading(volts=psu.measure_voltage(), amps=psu.measure_current(), on=psu.output_state())

    def psu_read(self, reading: PsuReading, now: float) -> None:
        """A supply reading taken (``measure_psu``): the supply's link is up, its suspenders look at it."""
        self.psu = reading
        self.link_ok("psu", now)

    def link_ok(self, source: str, now: float) -> None:
        """``source`` answered (a read or a command elsewhere): its link is up again."""
        self._link(source, None)
        self._watch(source, now)

    def record_telemetry(self, now: float, status: ChamberStatus | None, table: dict[int, AxisState] | None,
                         psu_reading: PsuReading | None) -> None:
        if status is not None or table or psu_reading is not None:
            self.store.add_telemetry(self.run_id, now, status, table, psu_reading)


class TelemetrySchedule:
    """The bench-time schedule of the chamber reads (every ``telemetry_period_s``) and of the turntable
    and power-supply reads (every ``table_psu_period_s``), both due at once at the start."""

    def __init__(self, engine_config: EngineConfig, now: float) -> None:
        self.cfg = engine_config
        self.next_chamber = now
        self.next_table_psu = now

    def due(self, now: float) -> tuple[bool, bool]:
        """Which reads are due at ``now`` (chamber, table/PSU); advances their schedules."""
        chamber = now >= self.next_chamber
        table_psu = now >= self.next_table_psu
        if chamber:
            self.next_chamber = _next_on_grid(self.next_chamber, now, self.cfg.telemetry_period_s)
        if table_psu:
            self.next_table_psu = _next_on_grid(self.next_table_psu, now, self.cfg.table_psu_period_s)
        return chamber, table_psu

    def next_due(self) -> float:
        return min(self.next_chamber, self.next_table_psu)

    def never(self) -> None:
        """Take these reads off this schedule (another owner reads the shared devices)."""
        self.next_chamber = self.next_table_psu = math.inf


def _next_on_grid(due: float, now: float, period: float) -> float:
    """The next instant of the schedule ``due + k * period`` after ``now``: a late tick does not shift
    the schedule (on the lockstep clock ticks are never late)."""
    nxt = due + period
    if nxt <= now:
        nxt = due + (math.floor((now - due) / period) + 1) * period
    return nxt

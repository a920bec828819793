"""In-process device doubles for engine tests (no tests here).

They implement the ``bench.interfaces`` Protocols with simple but real behaviour, advanced lazily
on the shared clock:

- ``Thermal``: chamber air follows the effective set point (first order, tau 300 s); a ramp
  profile moves the ramp set point at its rate; hold freezes it; gyro probes follow the air with
  their own lags (tau 600..900 s).  Faults: ``alarm``, ``input_error``.
- ``DoubleTable``: two axes moving at the rate limit towards the demanded position, or at a
  demanded rate.
- ``DoubleLink``: frames at ``rate_hz`` bench while the PSU output is on; ``silent`` stops them;
  ``down`` makes ``drain`` raise ``LinkDown``; gaps can be appended to ``stats.link_gaps``.
- ``DoubleProbes``: DS18B20-like 0.0625 C quantised readings of the thermal model; ``lost``
  names probes reported with a CRC fault.
"""
from __future__ import annotations

import math
import threading
from typing import Any, Callable

from bench.clock import SteppedClock
from bench.config import BenchConfig, TurntableConfig
from bench.devices.orientation import EIGHT_POSITION_GEOMETRY
from bench.engine import Devices, EngineConfig, MemoryRunStore
from bench.errors import LinkDown
from bench.interfaces import AxisState, ChamberStatus, GyroFrame, LinkStats, ProbeReading

SUB_S = 5.0


class Thermal:
    def __init__(self, clock, start_c: float = 25.0, probe_taus: tuple[float, ...] = (600.0, 700.0, 800.0, 900.0),
                 tau_air: float = 300.0) -> None:
        self.clock = clock
        self.t = clock.now()
        self.setpoint = start_c
        self.pv = start_c
        self.tau_air = tau_air
        self.probe_taus = probe_taus
        self.probes = [start_c] * len(probe_taus)
        self.ramp: dict[str, Any] | None = None   # {"sp", "target", "rate", "held"}
        self.alarm = 0
        self.input_error = 0
        self.power = False
        self.calls: list[tuple[float, str, tuple]] = []
        self.lock = threading.Lock()

    def effective_sp(self) -> float:
        return self.ramp["sp"] if self.ramp else self.setpoint

    def advance(self) -> None:
        now = self.clock.now()
        while self.t < now:
            dt = min(SUB_S, now - self.t)
            if self.ramp and not self.ramp["held"]:
                r = self.ramp
                step = r["rate"] / 60.0 * dt
                if abs(r["target"] - r["sp"]) <= step:
                    self.setpoint = r["target"]
                    self.ramp = None
                else:
                    r["sp"] += math.copysign(step, r["target"] - r["sp"])
            sp = self.effective_sp()
            self.pv = sp + (self.pv - sp) * math.exp(-dt / self.tau_air)
            self.probes = [p_c + (self.pv - p_c) * (1 - math.exp(-dt / tau))
                           for p_c, tau in zip(self.probes, self.probe_taus)]
            self.t += dt


class DoubleChamber:
    def __init__(self, thermal: Thermal, limits: tuple[float, float] = (-70.0, 180.0)) -> None:
        self.th = thermal
        self.limits = limits

    def _call(self, name: str, *args: Any) -> None:
        self.th.advance()
        self.th.calls.append((self.th.clock.now(), name, args))

    def read_temperature(self) -> float:
        self.th.advance()
        return round(self.th.pv, 1)

    def read_setpoint(self) -> float:
        self.th.advance()
        return self.th.setpoint

    def set_setpoint(self, celsius: float) -> None:
        self._call("set_setpoint", celsius)
        self.th.setpoint = float(celsius)

    def ramp_to(self, target_c: float, rate_c_per_min: float) -> None:
        self._call("ramp_to", target_c, rate_c_per_min)
        self.th.ramp = {"sp": self.th.setpoint, "target": float(target_c), "rate": float(rate_c_per_min),
                        "held": False}

    def hold(self) -> None:
        self._call("hold")
        if self.th.ramp:
            self.th.ramp["held"] = True

    def resume(self) -> None:
        self._call("resume")
        if self.th.ramp:
            self.th.ramp["held"] = False

    def stop(self) -> None:
        self._call("stop")
        if self.th.ramp:
            self.th.setpoint = self.th.ramp["sp"]
            self.th.ramp = None

    def set_power(self, on: bool) -> None:
        self._call("set_power", on)
        self.th.power = on

    def status(self) -> ChamberStatus:
        self.th.advance()
        r = self.th.ramp
        return ChamberStatus(pv_c=round(self.th.pv, 1), setpoint_c=self.th.setpoint,
                             ramp_setpoint_c=round(r["sp"], 1) if r else None,
                             mode=(3 if r["held"] else 2) if r else 1, alarm=self.th.alarm,
                             input_error=self.th.input_error, power_on=self.th.power)

    def setpoint_limits(self) -> tuple[float, float]:
        return self.limits

    def clear_alarm(self) -> None:
        self.th.alarm = 0

    def close(self) -> None:
        pass


class DoubleTable:
    axes = 2

    def __init__(self, clock, rate_limit: float = 100.0) -> None:
        self.clock = clock
        self.t = clock.now()
        self.rate_limit = rate_limit
        self.pos = {1: 0.0, 2: 0.0}
        self.target: dict[int, float | None] = {1: None, 2: None}
        self.rate_cmd = {1: 0.0, 2: 0.0}
        self.moving_rate = {1: 0.0, 2: 0.0}
        self.calls: list[tuple[float, str, tuple]] = []

    def advance(self) -> None:
        now = self.clock.now()
        dt = now - self.t
        self.t = now
        for a in (1, 2):
            tgt = self.target[a]
            if tgt is not None:
                err = (tgt - self.pos[a] + 180.0) % 360.0 - 180.0
                step = self.rate_limit * dt
                if abs(err) <= step:
                    self.pos[a] = tgt
                    self.moving_rate[a] = 0.0
                else:
                    self.pos[a] += math.copysign(step, err)
                    self.moving_rate[a] = math.copysign(self.rate_limit, err)
            else:
                self.pos[a] = (self.pos[a] + self.rate_cmd[a] * dt) % 360.0
                self.moving_rate[a] = self.rate_cmd[a]

    def _call(self, name: str, *args: Any) -> None:
        self.advance()
        self.calls.append((self.clock.now(), name, args))

    def identify(self) -> str:
        return "double table"

    def interlock_close(self, axis: int) -> None:
        self._call("interlock_close", axis)

    def interlock_open(self, axis: int) -> None:
        self._call("interlock_open", axis)

    def interlock_reset(self) -> None:
        self._call("interlock_reset")

    def move_to(self, axis: int, position_deg: float, *, wait: bool = True) -> None:
        self._call("move_to", axis, position_deg)
        self.target[axis] = float(position_deg)
        if wait:
            while self.read(axis).position_deg != position_deg:
                self.clock.sleep(0.5)

    def rate(self, axis: int, rate_dps: float) -> None:
        self._call("rate", axis, rate_dps)
        self.target[axis] = None
        self.rate_cmd[axis] = float(rate_dps)

    def off(self, axis: int) -> None:
        self.rate(axis, 0.0)

    def set_acceleration(self, axis: int, dps2: float) -> None:
        pass

    def set_rate_limit(self, axis: int, dps: float, mode: str = "P") -> None:
        pass

    def read(self, axis: int) -> AxisState:
        self.advance()
        return AxisState(self.pos[axis], self.moving_rate[axis])

    def close(self) -> None:
        pass


class DoublePsu:
    def __init__(self) -> None:
        self.on = False
        self.volts = 0.0
        self.amps = 0.0
        self.calls: list[tuple[str, tuple]] = []

    def identify(self) -> str:
        return "double psu"

    def output(self, on: bool) -> None:
        self.calls.append(("output", (on,)))
        self.on = bool(on)

    def set_voltage(self, volts: float) -> None:
        self.calls.append(("set_voltage", (volts,)))
        self.volts = volts

    def set_current_limit(self, amps: float) -> None:
        self.calls.append(("set_current_limit", (amps,)))
        self.amps = amps

    def measure_voltage(self) -> float:
        return self.volts if self.on else 0.0

    def measure_current(self) -> float:
        return 0.4 if self.on else 0.0

    def output_state(self) -> bool:
        return self.on

    def close(self) -> None:
        pass


class DoubleLink:
    def __init__(self, clock, psu: DoublePsu, thermal: Thermal, rate_hz: float = 5.0) -> None:
        self.clock = clock
        self.psu = psu
        self.thermal = thermal
        self.rate_hz = rate_hz
        self.stats = LinkStats()
        self.next_t = clock.now()
        self.seq = 0
        self.silent = False
        self.down = False
        self.started = 0

    def start(self) -> None:
        self.started += 1
        self.next_t = self.clock.now()   # a new process does not see frames sent before it opened the port

    def stop(self) -> None:
        pass

    def drain(self, max_frames: int | None = None) -> list[GyroFrame]:
        if self.down:
            raise LinkDown("double gyro link: port closed")
        now = self.clock.now()
        frames = []
        period = 1.0 / self.rate_hz
        while self.next_t <= now:
            if self.psu.on and not self.silent:
                self.seq = (self.seq + 1) % 128
                frames.append(GyroFrame(host_time=self.next_t, sequence=self.seq, gyro=(0.001, -0.002, 0.003),
                                        accel=(0.0, 0.0, 1.0), status=0x77,
                                        temperature_c=self.thermal.probes[0], raw=b"\x00" * 36))
            self.next_t += period
        self.stats.frames += len(frames)
        return frames


class DoubleProbes:
    def __init__(self, thermal: Thermal, names: tuple[str, ...] = ("t1", "t2", "t3", "t4")) -> None:
        self.th = thermal
        self.names = names
        self.lost: set[str] = set()

    def read_all(self) -> list[ProbeReading]:
        self.th.advance()
        out = []
        for i, name in enumerate(self.names):
            serial = f"0000000000{i + 1:02x}"
            if name in self.lost:
                out.append(ProbeReading(name, serial, None, "CRC NO"))
            else:
                out.append(ProbeReading(name, serial, round(self.th.probes[i] / 0.0625) * 0.0625))
        return out


class Bench:
    """Everything a test needs: clock, doubles, devices bundle, store, config."""

    def __init__(self, start_c: float = 25.0, **engine_overrides: Any) -> None:
        self.clock = SteppedClock(1_700_000_000.0)
        self.thermal = Thermal(self.clock, start_c)
        self.chamber = DoubleChamber(self.thermal)
        self.table = DoubleTable(self.clock)
        self.psu = DoublePsu()
        self.link = DoubleLink(self.clock, self.psu, self.thermal)
        self.probes = DoubleProbes(self.thermal)
        self.devices = Devices(self.chamber, self.table, self.link, self.probes, self.psu)
        self.store = MemoryRunStore()
        self.config = BenchConfig(
            turntable=TurntableConfig(geometry=EIGHT_POSITION_GEOMETRY),
            probes={"probes": {n: f"0000000000{i + 1:02x}" for i, n in enumerate(self.probes.names)}})
        params = dict(tick_s=1.0, max_tick_s=10.0, probe_period_s=2.0, telemetry_period_s=5.0,
                      checkpoint_period_s=60.0, settle_s=60.0, frames_timeout_s=10.0, frames_grace_s=5.0)
        params.update(engine_overrides)
        self.engine_config = EngineConfig(**params)

    def engine(self, control=None, fit_hook=None):
        from bench.engine import Engine
        return Engine(self.devices, self.store, self.clock, self.config, control, self.engine_config, fit_hook)

    def run(self, run_id: str):
        return self.store.runs[run_id]


class Scripted:
    """A control that fires actions at bench-time offsets: each action is a control request
    ("stop", "pause"...) or a callable (fault injection) run when its time has come."""

    def __init__(self, clock, actions: list[tuple[float, Any]]) -> None:
        self.clock = clock
        self.t0 = clock.now()
        self.actions = sorted(actions, key=lambda a: a[0])
        self.fired: list[tuple[float, Any]] = []

    def poll(self) -> str | None:
        now = self.clock.now()
        while self.actions and now - self.t0 >= self.actions[0][0]:
            offset, action = self.actions.pop(0)
            self.fired.append((now - self.t0, action))
            if callable(action):
                action()
                continue
            return action
        return None


class Killed(BaseException):
    """Stands for kill -9: not an Exception, so the engine does no cleanup at all."""


def kill_at(offset_s: float) -> Callable[[], None]:
    def die() -> None:
        raise Killed(f"killed at +{offset_s} s")
    return die

"""Simulated thermal chamber: a Watlow F4 Modbus front-end (``ChamberSimulator``) served over
Modbus TCP and Modbus RTU-over-TCP with pymodbus 3.16, on top of the chamber physics and controller
model (``bench.sim.chamber_physics.ChamberModel``, beside the gyro physics in ``bench.sim.physics``).

Protocol facts used (``../shared/reference/device-protocols.md`` section 1, Watlow F4 via the
TestEquity F4 resources and Espec's ``watlowf4.py``; pymodbus facts from section 5.1):

* Holding registers, register number = PDU address (reading 100 over RTU is ``01 03 00 64 00 01 C5 D5``).
  FC3 and FC4 see the same registers (shared ``SimData`` block, as the F4 does), FC6/FC16 write.
* Temperatures are signed int16 with implied decimals from 606 (default 1: 25.6 C <-> 256), in C
  when 901 = 1, in F when 901 = 0 (deviations and rates scale by 9/5 without offset).
* Unknown registers -> exception 02 (pymodbus marks every address not listed below invalid);
  writes to read-only registers -> 02; out-of-range values -> exception 03.

Registers implemented
    0 model (5270), 1/2 serial number, 3/4/5 software number/revision/date, 8/9/10 input types (R)
    25 save to EEPROM (W 0, accepted, no effect)
    100 PV input 1 (R), 101 input 1 error (R), 102 alarm 1 status (R), 103/107 output 1A/1B power %x100 (R)
    200 operation mode (R), 300 set point 1 (R/W, inside 602..603), 302/303 alarm 1 low/high deviation,
    308 idle set point, 311/312/313 clear input error / clear alarm / silence alarm (W 1)
    600/601 sensor/sensor type, 602/603 SP low/high limit, 604 filter, 605 calibration offset (added to
    the PV), 606 decimals 0..3, 607 error latching, 608 process units, 900 PID units, 901 C=1/F=0
    1209/1210/1217 resume/hold/terminate profile (W 1), 1218/1219 profiles/steps remaining (R)
    2000+10(n-1) event n = 1..8 (event 1 = chamber power, TestEquity wiring)
    3500..3899 profile names (10 registers a profile, one ASCII char each: A-Z, 0-9, space or 0)
    4000 profile #, 4001 step #, 4002 edit action, 4003..4016, 4021..4026, 4030..4037, 4043..4052,
    4060..4062 per-step registers of the selected profile/step; 4100..4130 live profile status
    (4100 profile, 4101 step, 4102 step type, 4119..4121 step time left h/m/s, 4122 ramping SP,
    4129 end SP).

Uncertain points and how this simulator resolves them
    * 200 enumeration: Espec maps 0/1 = constant, 2 = profile running, 3 = profile held.  We report
      0 in constant mode (never 1), 2 running, 3 held.
    * 102 enumeration is not published: 0 = no alarm, 1 = low-side deviation, 2 = high-side deviation;
      an injected alarm reads the injected code.  Alarm 1 is a latching deviation alarm (band 302/303
      around the active set point), armed only once the PV has been inside the band since the last
      set point change (F4 "alarm silencing" behaviour) so a normal step change does not trip it.
      Writing 312 = 1 clears it only if the condition is gone.
    * 4043 units: rate x10 in degrees per minute (Espec writes ``int(rate*10)``), unsigned; 0 refused.
    * 4002 = 1 "create" makes a profile holding one end step (hold), numbered by 4000 if that number
      is free, else the lowest free number, and writes the number back to 4000 (Espec reads 4000
      after creating).  4002 = 2 inserts a soak step (0 s) before step 4001; 3 deletes the selected
      profile (no-op if absent, 03 if it is running); 4 deletes step 4001; 5 starts the selected
      profile at step 4001; 256 deletes all.  Editing the running profile -> 03.
    * Step type 5 (end) cannot be written onto a non-end step nor changed on the end step (03): steps
      are inserted before the end step, which stays last.
    * Reading per-step registers of a step that does not exist gives 4003 = 6 (greater than every
      step type, which is how Espec detects "no such profile"); the others read 0.
    * A ramp-rate step starts from the current PV.  Step types 1 ramp-time, 2 ramp-rate, 3 soak and
      5 end run; a profile holding 0 autostart or 4 jump steps is refused at start (03).
    * End action 0 "hold": the profile ends, the static set point 300 takes the last profile set
      point and the mode returns to 0, so the chamber holds there.  1 control off / 2 all off turn the
      control outputs off (air drifts to ambient) until the next 300 write or profile start (2 also
      switches event 1, chamber power, off; events 2..8 are not touched); 3 idle
      sets 300 to the step's idle set point.  1217 terminate returns to static control at 300.
    * 101 input error: an injected sensor fault latches 101 (code), turns the control outputs off and
      makes register 100 read +32767 (open-sensor upscale); 311 = 1 clears it once the fault is gone.
    * A request for another unit id gets no answer (a real RTU slave stays silent), on both transports.
"""
from __future__ import annotations

import asyncio
import collections
import functools
import math
import threading

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from bench.clock import Clock
from bench.errors import IllegalValue
from bench.sim.audit import CommandLog
from bench.sim.chamber_physics import (END_HOLD, STEP_END, STEP_RAMP_RATE, STEP_RAMP_TIME, STEP_SOAK, ChamberModel,
                                      ProfileStep)
# Simulated-bench snapshots pickle the model's profile objects by module: these names keep the
# snapshots taken while the model lived here restorable.
from bench.sim.chamber_physics import _RunningProfile  # noqa: F401


# --------------------------------------------------------------------------------------------
# F4 register map (raw uint16 <-> model)
# --------------------------------------------------------------------------------------------

_IDENTITY = {0: 5270, 1: 4102, 2: 2024, 3: 1, 4: 12, 5: 603, 8: 0, 9: 0, 10: 0}
_LIVE = {100, 101, 102, 103, 107, 200, 1218, 1219} | set(range(4100, 4131))
_READ_ONLY = set(_IDENTITY) | _LIVE
# Plain stored configuration registers: reg -> (min, max, default)
_PLAIN = {600: (0, 4, 0), 601: (0, 20, 0), 604: (0, 60, 0), 607: (0, 1, 0), 608: (0, 3, 0),
          900: (0, 1, 1)}
_COMMANDS = {25, 311, 312, 313, 1209, 1210, 1217}
_EVENTS = {2000 + 10 * n: n + 1 for n in range(8)}
_NAMES = range(3500, 3900)
_STEP_REGS = (set(range(4003, 4017)) | set(range(4021, 4027)) | set(range(4030, 4038))
              | set(range(4043, 4053)) | set(range(4060, 4063)))
_STEP_TEMPS = {4022, 4024, 4026, 4044, 4045, 4061, 4062}
# per-step integer registers: reg -> (min, max); anything else in _STEP_REGS is 0..65535
_STEP_RANGES = {4003: (0, 5), 4004: (0, 1), 4009: (0, 999), 4010: (0, 59), 4011: (0, 59), 4012: (0, 1),
                4013: (0, 2), 4014: (0, 2), 4015: (0, 2), 4016: (0, 2), 4021: (0, 1), 4023: (0, 1),
                4025: (0, 1), 4043: (1, 65535), 4046: (0, 9), 4047: (0, 9), 4048: (0, 1), 4049: (0, 1),
                4050: (0, 40), 4051: (0, 256), 4052: (0, 9999), 4060: (0, 3)}
_STEP_REGS_NO_STEP = 6        # 4003 value read for a step that does not exist
_MAX_PROFILES = 40
_MAX_STEPS_TOTAL = 256
_WRITABLE = ({300, 302, 303, 308, 602, 603, 605, 606, 901} | set(_PLAIN) | _COMMANDS | set(_EVENTS)
             | set(_NAMES) | {4000, 4001, 4002} | _STEP_REGS)


def _signed(raw: int) -> int:
    return raw - 0x10000 if raw >= 0x8000 else raw


def _runs(addresses: set[int]) -> list[tuple[int, int]]:
    """Contiguous (start, count) runs of a set of register numbers."""
    runs: list[tuple[int, int]] = []
    for reg in sorted(addresses):
        if runs and runs[-1][0] + runs[-1][1] == reg:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((reg, 1))
    return runs


class _F4Registers:
    """Watlow F4 register semantics on top of a ``ChamberModel`` (not thread-safe by itself)."""

    def __init__(self, model: ChamberModel, decimals: int = 1, celsius: bool = True) -> None:
        if not 0 <= decimals <= 3:
            raise ValueError(f"F4 decimals (606) must be 0..3, got {decimals}")
        self.model = model
        self.decimals = decimals
        self.celsius = celsius
        self.plain = {reg: spec[2] for reg, spec in _PLAIN.items()}
        self.idle_sp_c = 23.0
        self.events = [0] * 8
        self.names: dict[int, int] = {}
        self.profiles: dict[int, list[dict[int, float]]] = {}
        self.sel_profile = 1
        self.sel_step = 1

    # ---- encoding ---------------------------------------------------------------------------
    def enc(self, celsius: float, delta: bool = False) -> int:
        value = celsius if self.celsius else celsius * 9.0 / 5.0 + (0.0 if delta else 32.0)
        raw = round(value * 10 ** self.decimals)
        return max(-32768, min(32767, raw)) & 0xFFFF

    def dec(self, raw: int, delta: bool = False) -> float:
        value = _signed(raw) / 10 ** self.decimals
        return value if self.celsius else (value if delta else value - 32.0) * 5.0 / 9.0

    # ---- reads ------------------------------------------------------------------------------
    def read(self, reg: int) -> int:
        m = self.model
        if reg in _IDENTITY:
            return _IDENTITY[reg]
        if reg == 100:
            return 0x7FFF if m.input_error else self.enc(m.pv_c)
        if reg == 101:
            return m.input_error
        if reg == 102:
            return m.alarm
        if reg in (103, 107):
            return round(m.output_percent[0 if reg == 103 else 1] * 100)
        if reg == 200:
            return m.mode
        if reg == 300:
            return self.enc(m.setpoint_c)
        if reg in (302, 303):
            return self.enc(m.alarm_band_c[reg - 302], delta=True)
        if reg == 308:
            return self.enc(self.idle_sp_c)
        if reg in _COMMANDS:
            return 0
        if reg in self.plain:
            return self.plain[reg]
        if reg in (602, 603):
            return self.enc(m.setpoint_limits[reg - 602])
        if reg == 605:
            return self.enc(m.cal_offset_c, delta=True)
        if reg == 606:
            return self.decimals
        if reg == 901:
            return 1 if self.celsius else 0
        if reg == 1218:
            return _MAX_PROFILES - len(self.profiles)
        if reg == 1219:
            return _MAX_STEPS_TOTAL - sum(len(s) for s in self.profiles.values())
        if reg in _EVENTS:
            return int(m.power_on) if reg == 2000 else self.events[_EVENTS[reg] - 1]
        if reg in _NAMES:
            return self.names.get(reg, 0)
        if reg == 4000:
            return self.sel_profile
        if reg == 4001:
            return self.sel_step
        if reg == 4002:
            return 0
        if reg in _STEP_REGS:
            step = self._selected_step()
            if step is None:
                return _STEP_REGS_NO_STEP if reg == 4003 else 0
            value = step.get(reg, 0)
            if reg in _STEP_TEMPS:
                return self.enc(value)
            if reg == 4043:
                return max(0, min(65535, round((value if self.celsius else value * 9 / 5) * 10)))
            return int(value)
        if 4100 <= reg <= 4130:
            return self._live(reg)
        raise KeyError(reg)

    def _live(self, reg: int) -> int:
        number, step_no, kind, left = self.model.profile_position
        if reg == 4100:
            return number
        if reg == 4101:
            return step_no
        if reg == 4102:
            return kind
        if reg in (4119, 4120, 4121):
            secs = int(math.ceil(left)) if left is not None else 0
            return (min(secs // 3600, 0xFFFF), secs // 60 % 60, secs % 60)[reg - 4119]
        if reg == 4122:
            ramp = self.model.ramp_setpoint_c
            return self.enc(self.model.setpoint_c if ramp is None else ramp)
        if 4111 <= reg <= 4118:
            return self.read(2000 + 10 * (reg - 4111))
        if reg in (4124, 4125):
            return 1
        if reg == 4129:
            if number and number in self.profiles:
                targets = [s.get(4044, 0.0) for s in self.profiles[number]
                           if s.get(4003) in (STEP_RAMP_TIME, STEP_RAMP_RATE)]
                if targets:
                    return self.enc(targets[-1])
            return self.enc(self.model.setpoint_c)
        return 0

    def _selected_step(self) -> dict[int, float] | None:
        steps = self.profiles.get(self.sel_profile)
        if steps is None or not 1 <= self.sel_step <= len(steps):
            return None
        return steps[self.sel_step - 1]

    # ---- writes -----------------------------------------------------------------------------
    def write(self, reg: int, raw: int) -> None:
        """Apply one register write; raises ``IllegalValue`` (-> exception 03) when refused."""
        m = self.model

        def need(ok: bool, why: str) -> None:
            if not ok:
                raise IllegalValue(f"register {reg} = {raw}: {why}", code=3)

        if reg == 300:
            m.set_setpoint(self.dec(raw))
        elif reg in (302, 303):
            band = list(m.alarm_band_c)
            band[reg - 302] = self.dec(raw, delta=True)
            m.set_alarm_band(*band)
        elif reg == 308:
            low, high = m.setpoint_limits
            need(low <= self.dec(raw) <= high, "idle set point outside 602..603")
            self.idle_sp_c = self.dec(raw)
        elif reg == 25:
            need(raw == 0, "write 0 to save to EEPROM")
        elif reg in _COMMANDS:
            need(raw in (0, 1), "command registers take 1 (0 does nothing)")
            if raw:
                self._command(reg)
        elif reg in self.plain:
            low, high, _ = _PLAIN[reg]
            need(low <= raw <= high, f"allowed {low}..{high}")
            self.plain[reg] = raw
        elif reg in (602, 603):
            limits = list(m.setpoint_limits)
            limits[reg - 602] = self.dec(raw)
            m.set_setpoint_limits(*limits)
        elif reg == 605:
            m.set_cal_offset(self.dec(raw, delta=True))
        elif reg == 606:
            need(0 <= raw <= 3, "decimals 0..3")
            self.decimals = raw
        elif reg == 901:
            need(raw in (0, 1), "1 = C, 0 = F")
            self.celsius = raw == 1
        elif reg in _EVENTS:
            need(raw in (0, 1), "events are 0 off / 1 on")
            if reg == 2000:
                m.set_power(bool(raw))
            self.events[_EVENTS[reg] - 1] = raw
        elif reg in _NAMES:
            need(raw in (0, 32) or 48 <= raw <= 57 or 65 <= raw <= 90, "names use A-Z, 0-9 or space")
            self.names[reg] = raw
        elif reg == 4000:
            need(1 <= raw <= _MAX_PROFILES, f"profile number 1..{_MAX_PROFILES}")
            self.sel_profile = raw
        elif reg == 4001:
            need(1 <= raw <= _MAX_STEPS_TOTAL, "step number 1..256")
            self.sel_step = raw
        elif reg == 4002:
            self._edit(raw, need)
        elif reg in _STEP_REGS:
            self._write_step(reg, raw, need)
        else:   # read-only registers are refused by pymodbus before we get here
            raise IllegalValue(f"register {reg} is not writable", code=3)

    def _command(self, reg: int) -> None:
        m = self.model
        if reg == 311:
            m.clear_input_error()
        elif reg == 312:
            m.clear_alarm()
        elif reg == 1209:
            m.resume_profile()
        elif reg == 1210:
            m.hold_profile()
        elif reg == 1217:
            m.terminate_profile()

    def _edit(self, action: int, need) -> None:
        running = self.model.running_profile_number
        number = self.sel_profile
        if action == 1:                                     # create
            need(len(self.profiles) < _MAX_PROFILES, "no free profile")
            if number in self.profiles:
                number = min(n for n in range(1, _MAX_PROFILES + 1) if n not in self.profiles)
            self.profiles[number] = [{4003: STEP_END, 4060: END_HOLD}]
            self.sel_profile, self.sel_step = number, 1
        elif action == 2:                                   # insert step before 4001
            steps = self.profiles.get(number)
            need(steps is not None, f"profile {number} does not exist")
            need(number != running, f"profile {number} is running")
            need(1 <= self.sel_step <= len(steps), f"profile {number} has no step {self.sel_step}")
            need(sum(len(s) for s in self.profiles.values()) < _MAX_STEPS_TOTAL, "no free step")
            steps.insert(self.sel_step - 1, {4003: STEP_SOAK})
        elif action == 3:                                   # delete profile
            need(number != running, f"profile {number} is running")
            self.profiles.pop(number, None)
        elif action == 4:                                   # delete step
            steps = self.profiles.get(number)
            need(steps is not None and 1 <= self.sel_step < len(steps),
                 f"profile {number} has no deletable step {self.sel_step}")
            need(number != running, f"profile {number} is running")
            del steps[self.sel_step - 1]
        elif action == 5:                                   # start
            steps = self.profiles.get(number)
            need(steps is not None, f"profile {number} does not exist")
            self.model.start_profile(number, [self._to_step(s) for s in steps], self.sel_step)
        elif action == 256:                                 # delete all
            need(running == 0, f"profile {running} is running")
            self.profiles.clear()
        else:
            need(False, "edit actions are 1, 2, 3, 4, 5, 256")

    def _write_step(self, reg: int, raw: int, need) -> None:
        step = self._selected_step()
        need(step is not None, f"profile {self.sel_profile} has no step {self.sel_step}")
        need(self.sel_profile != self.model.running_profile_number, f"profile {self.sel_profile} is running")
        if reg in _STEP_TEMPS:
            value = self.dec(raw)
            if reg in (4044, 4061):
                low, high = self.model.setpoint_limits
                need(low <= value <= high, f"set point {value:.2f} C outside 602..603")
            step[reg] = value
            return
        low, high = _STEP_RANGES.get(reg, (0, 65535))
        need(low <= raw <= high, f"allowed {low}..{high}")
        if reg == 4003:
            need((raw == STEP_END) == (step.get(4003) == STEP_END),
                 "the end step stays last: insert steps before it")
        step[reg] = raw / 10.0 * (1.0 if self.celsius else 5.0 / 9.0) if reg == 4043 else raw

    @staticmethod
    def _to_step(regs: dict[int, float]) -> ProfileStep:
        kind = int(regs.get(4003, STEP_SOAK))
        duration = regs.get(4009, 0) * 3600 + regs.get(4010, 0) * 60 + regs.get(4011, 0)
        return ProfileStep(kind=kind, target_c=float(regs.get(4044, 0.0)),
                           rate_c_per_min=float(regs.get(4043, 0.0)), duration_s=float(duration),
                           end_action=int(regs.get(4060, END_HOLD)),
                           idle_setpoint_c=float(regs.get(4061, 23.0)))


# --------------------------------------------------------------------------------------------
# Fault injection and the Modbus servers
# --------------------------------------------------------------------------------------------

class ChamberFaults:
    """Fault injection for ``ChamberSimulator`` (affects both transports).

    * ``modbus_exception(code=4, count=1)``: the next ``count`` requests are answered with Modbus
      exception ``code`` (not executed).
    * ``delay_s``: every reply is sent this many wall seconds late (0 = off).
    * ``drop_requests``: the next N requests are ignored (not executed, no reply).
    * ``drop_replies``: the next N requests are executed but their reply is lost.
    * ``drop_link(duration_s)``: close every connection and stop listening for ``duration_s`` wall
      seconds, then listen again on the same ports.  ``link_down`` tells whether it is down now.
    * ``input_error`` (int): sensor fault code on input 1 (latches 101; 0 = sensor repaired).
    * ``alarm`` (int): forced alarm 1 condition (102 = code; 0 = condition removed, still latched).
    * ``requests_seen``: number of requests addressed to our unit id (for tests).
    """

    def __init__(self, simulator: "ChamberSimulator") -> None:
        self._sim = simulator
        self._lock = threading.Lock()
        self.delay_s = 0.0
        self.drop_requests = 0
        self.drop_replies = 0
        self.requests_seen = 0
        self._exception_code = 0
        self._exception_count = 0
        self._input_error = 0
        self._alarm = 0

    def modbus_exception(self, code: int = 4, count: int = 1) -> None:
        if not 1 <= code <= 255 or count < 0:
            raise ValueError(f"Modbus exception code must be 1..255 and count >= 0, got {code}, {count}")
        with self._lock:
            self._exception_code, self._exception_count = code, count

    def drop_link(self, duration_s: float) -> None:
        self._sim._drop_link(duration_s)

    @property
    def link_down(self) -> bool:
        return self._sim._link_is_down

    @property
    def input_error(self) -> int:
        return self._input_error

    @input_error.setter
    def input_error(self, code: int) -> None:
        self._input_error = int(code)
        self._sim.model.inject_sensor_fault(int(code))

    @property
    def alarm(self) -> int:
        return self._alarm

    @alarm.setter
    def alarm(self, code: int) -> None:
        self._alarm = int(code)
        self._sim.model.inject_alarm(int(code))

    def _decide(self) -> tuple[bool, int, float, bool]:
        """Per request: (ignore it, exception code or 0, delay, lose the reply)."""
        with self._lock:
            self.requests_seen += 1
            if self.drop_requests > 0:
                self.drop_requests -= 1
                return True, 0, 0.0, False
            code = 0
            if self._exception_count > 0:
                self._exception_count -= 1
                code = self._exception_code
            lose = False
            if self.drop_replies > 0:
                self.drop_replies -= 1
                lose = True
            return False, code, float(self.delay_s), lose


class ChamberSimulator:
    """Watlow F4 Modbus front-end for a ``ChamberModel``.

    Serves Modbus TCP (``start_tcp``) and Modbus RTU framing over a TCP socket (``start_rtu``; a
    pyserial ``socket://`` URL on the client side) from one background asyncio thread, on
    127.0.0.1 ephemeral ports.  ``start()`` starts both.  ``tcp_address`` is "host:port",
    ``rtu_url`` is "socket://host:port" (aliases ``address`` / ``url``).  Every request first
    advances the model to ``clock.now()``; writes are validated and applied to the model in the
    pymodbus ``SimDevice`` ``action`` hook (pymodbus >= 3.13), reads are refreshed from it.
    ``faults`` is a ``ChamberFaults``.  ``last_refusal`` holds the reason of the last exception 03;
    ``wire_log`` the last 200 raw chunks received ("rx") and frames sent ("tx"), both transports.
    Function codes other than 3, 4, 6, 16, 23 get exception 01.  An FC16 write stops at the first
    refused register (03); the registers before it in the same request stay written.
    """

    def __init__(self, model: ChamberModel, clock: Clock, unit_id: int = 1, *, host: str = "127.0.0.1",
                 decimals: int = 1, celsius: bool = True) -> None:
        if not 1 <= unit_id <= 247:
            raise ValueError(f"Modbus unit id must be 1..247, got {unit_id}")
        self.model = model
        self.clock = clock
        self.unit_id = unit_id
        self.host = host
        self.registers = _F4Registers(model, decimals, celsius)
        self.faults = ChamberFaults(self)
        self.last_refusal: str | None = None
        self.wire_log: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=200)
        # every request, by transport ("modbus_tcp" / "modbus_rtu"; the pymodbus hooks do not name the
        # connection), as the function code and registers
        self.received = CommandLog("chamber")
        self._lock = threading.RLock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: dict[str, ModbusTcpServer | ModbusSerialServer] = {}
        self._ports: dict[str, int] = {}
        self._link_is_down = False
        self._drop_next_packet = False
        self._relisten_handle: asyncio.TimerHandle | None = None

    # ---- datastore --------------------------------------------------------------------------
    def _device(self) -> SimDevice:
        blocks = [SimData(start, count=count, values=0, datatype=DataType.REGISTERS,
                          readonly=start in _READ_ONLY)
                  for addresses in (_READ_ONLY, _WRITABLE) for start, count in _runs(addresses)]
        return SimDevice(id=self.unit_id, simdata=blocks, action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        if function_code not in (3, 4, 6, 16, 23):
            return ExcCodes.ILLEGAL_FUNCTION
        with self._lock:
            self.model.advance_to(self.clock.now())
            if set_values is not None:
                for i, raw in enumerate(set_values):
                    try:
                        self.registers.write(address + i, int(raw))
                    except IllegalValue as exc:
                        self.last_refusal = str(exc)
                        return ExcCodes.ILLEGAL_VALUE
                for i in range(len(set_values)):
                    set_values[i] = self.registers.read(address + i)
                return None
            for i in range(count):
                registers[address - start_address + i] = self.registers.read(address + i)
        return None

    def read_register(self, reg: int) -> int:
        """Current raw value of a register (test/debug helper, advances the model first)."""
        with self._lock:
            self.model.advance_to(self.clock.now())
            return self.registers.read(reg)

    # ---- request hooks (run in the server loop) ------------------------------------------------
    def _trace_pdu(self, transport: str, sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        if sending:
            self._drop_next_packet = bool(getattr(pdu, "_bench_lost_reply", False))
            return pdu
        if pdu.dev_id != self.unit_id:
            return None                       # not for us: stay silent like an RTU slave
        self.received.record(transport, f"fc{pdu.function_code} @{getattr(pdu, 'address', '?')}")
        ignore, code, delay, lose = self.faults._decide()
        if ignore:
            return None
        if code or delay or lose:
            original = pdu.datastore_update

            async def faulty_update(context, device_id):
                if delay:
                    await asyncio.sleep(delay)
                reply = ExceptionResponse(pdu.function_code, code) if code else await original(context, device_id)
                if lose:
                    reply._bench_lost_reply = True
                return reply

            pdu.datastore_update = faulty_update
        return pdu

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending and self._drop_next_packet:
            self._drop_next_packet = False
            return b""
        self.wire_log.append(("tx" if sending else "rx", bytes(data)))
        return data

    # ---- servers -----------------------------------------------------------------------------
    async def _listen(self, kind: str, port: int) -> int:
        hooks = {"trace_pdu": functools.partial(self._trace_pdu, f"modbus_{kind}"),
                 "trace_packet": self._trace_packet}
        if kind == "tcp":
            server = ModbusTcpServer(self._device(), address=(self.host, port), **hooks)
        else:
            server = ModbusSerialServer(self._device(), framer=FramerType.RTU,
                                        port=f"socket://{self.host}:{port}", **hooks)
        await server.serve_forever(background=True)
        self._servers[kind] = server
        return server.transport.sockets[0].getsockname()[1]

    def _run(self, coro, timeout: float = 5.0):
        assert self._loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    def _ensure_loop(self) -> None:
        if self._loop is not None:
            return
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="chamber-sim", daemon=True)
        self._thread.start()

    def _start(self, kind: str) -> None:
        with self._lock:
            self._ensure_loop()
            if kind not in self._servers:
                self._ports[kind] = self._run(self._listen(kind, self._ports.get(kind, 0)))

    def start_tcp(self) -> str:
        self._start("tcp")
        return self.tcp_address

    def start_rtu(self) -> str:
        self._start("rtu")
        return self.rtu_url

    def start(self) -> "ChamberSimulator":
        self.start_tcp()
        self.start_rtu()
        return self

    @property
    def tcp_address(self) -> str:
        if "tcp" not in self._ports:
            raise RuntimeError("chamber simulator: Modbus TCP server not started")
        return f"{self.host}:{self._ports['tcp']}"

    @property
    def rtu_url(self) -> str:
        if "rtu" not in self._ports:
            raise RuntimeError("chamber simulator: Modbus RTU server not started")
        return f"socket://{self.host}:{self._ports['rtu']}"

    address = tcp_address
    url = rtu_url

    async def _shutdown_servers(self) -> None:
        for server in list(self._servers.values()):
            await server.shutdown()
        self._servers.clear()

    async def _cancel_pending(self) -> None:
        """Cancel request handlers still running (e.g. delayed replies) before the loop stops."""
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _drop_link(self, duration_s: float) -> None:
        if duration_s < 0:
            raise ValueError("link drop duration must be >= 0 s")

        async def drop() -> None:
            kinds = list(self._servers)
            await self._shutdown_servers()
            self._link_is_down = True

            async def relisten() -> None:
                for kind in kinds:
                    if kind not in self._servers:
                        self._ports[kind] = await self._listen(kind, self._ports[kind])
                self._link_is_down = False

            self._relisten_handle = asyncio.get_running_loop().call_later(
                duration_s, lambda: asyncio.ensure_future(relisten()))

        with self._lock:
            if self._loop is None:
                raise RuntimeError("chamber simulator not started")
            self._run(drop())

    def stop(self) -> None:
        with self._lock:
            if self._loop is None:
                return
            if self._relisten_handle is not None:
                self._loop.call_soon_threadsafe(self._relisten_handle.cancel)
            try:
                self._run(self._shutdown_servers())
                self._run(self._cancel_pending())
            finally:
                self._loop.call_soon_threadsafe(self._loop.stop)
                assert self._thread is not None
                self._thread.join(5.0)
                self._loop.close()
                self._loop = None
                self._thread = None
                self._link_is_down = False

    def __enter__(self) -> "ChamberSimulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

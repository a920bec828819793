"""Watlow F4 thermal-chamber driver over Modbus RTU or Modbus TCP (pymodbus 3.16 sync clients).

Protocol facts (``../shared/reference/device-protocols.md`` section 1; TestEquity F4 resources,
Espec ``watlowf4.py``):

* Holding registers; the register number goes on the wire as-is (reading 100 over RTU is
  ``01 03 00 64 00 01 C5 D5``).  FC3 reads, FC6 single writes, FC16 for the 4001/4002 pair.
* Temperatures are signed int16 with implied decimals: value = raw * 10**-dp, dp read from 606
  (Espec's ``1/(dp*10)`` is wrong for dp >= 2).  901 = 1 means C, 0 means F (converted here).
* RTU link: 8N1 at ``config.baudrate``; ``config.address`` is a serial device or a pyserial URL
  (``socket://host:port`` = RTU frames over TCP).  TCP link: ``config.address`` = "host:port".
* Watlow recommends ~30 ms between transactions: ``config.inter_frame_delay_s`` (wall time) is kept
  between the end of one transaction and the start of the next.

Registers used
    0 model (5270 on an F4; recorded in ``model_number``, not enforced so an F4T in "F4 compatibility"
    data map also works), 100 PV, 101 input error, 102 alarm 1, 200 mode, 300 set point,
    602/603 set-point limits, 606 decimals, 901 units, 311/312 clear input error / clear alarm,
    1209/1210/1217 resume/hold/terminate profile, 2000 event 1 (chamber power, TestEquity wiring),
    4000/4001/4002 profile #/step #/edit action, 4003 step type, 4043 ramp rate, 4044 target,
    4060 end action, 4100/4101 current profile/step, 4122 current ramping set point.

Ramp choice (``config.ramp_mode``)
    "profile" (default): ``ramp_to`` programs F4 profile ``config.profile_number`` as
    [step 1: ramp-rate (4003 = 2) to the target (4044) at the rate (4043 = rate x 10, C/min),
     step 2: end (4003 = 5) with end action hold (4060 = 0)] and starts it with 4000 = N, 4001 = 1,
    4002 = 5.  The controller then moves its ramping set point (4122) itself, so the ramp survives a
    host crash or a lost link.  Programming sequence (Espec's order): 4000 = N, 4002 = 3 (delete),
    4002 = 1 (create; the controller may renumber, so 4000 is read back), 4001/4002 = 1/2 (insert
    step 1 before the end step), 4003/4043/4044, 4001 = 2 and 4060 = 0 on the end step, then start.
    An active profile is first stopped as in ``stop``.  The ramp is over when 200 returns to 0/1.
    "host": ``ramp_to`` writes 300 = the current PV and remembers (start, target, rate, bench time);
    ``ramp_tick()`` (also called by ``status()``) writes 300 = start +/- rate * elapsed, clamped
    at the target, whenever the value changes by at least one display count.  ``hold``/``resume``
    freeze/continue the host ramp (held time does not count), ``stop`` abandons it leaving 300 where
    it is.  The caller must poll ``ramp_tick()`` or ``status()`` often enough for its resolution.
    ``stop`` (both modes): if a profile runs or is held, 300 is first set to the present ramping set
    point (4122) and the profile is terminated (1217 = 1), so the chamber holds where it is instead
    of jumping back to an old static set point.

Status (``status()``, polled every few seconds): every call reads 100..102 (PV, input error, alarm) and
300 (set point); 200 (mode) and 2000 (event 1) only when the last values read are older than
``config.status_refresh_s`` bench seconds, after any write of this driver (which may change them), after
a reconnect, and at every call while a profile runs or is held (the controller ends the profile, sets
300 and may switch events by itself then; 4122 is read too).  In constant mode the controller changes
neither on its own, only this host or the operator at the front panel does, so the steady poll costs
two transactions instead of four and a front-panel change shows within ``status_refresh_s``.

Uncertain points: 200 = 0 or 1 is constant, 2 running, 3 held (Espec's mapping); 102 is only
tested for 0 / non-zero; 4043 is taken as tenths of a degree per minute (Espec writes
``int(rate*10)``).  ``max_ramp_c_per_min`` from the config bounds requested rates.

Errors: Modbus exception 02 -> ``IllegalAddress``, 03 -> ``IllegalValue``, other codes ->
``ModbusException``; no reply after ``retries`` -> ``DeviceTimeout``; connect failure or a link that
breaks -> ``LinkDown``.  Messages name the chamber address, unit id, register and operation.  After
a timeout or a broken link the connection is closed (stale late replies cannot be taken for the next
answer) and reopened by the next call, which also re-reads 606/901.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.framer import FramerType

from bench.clock import Clock, RealClock
from bench.config import ChamberConfig
from bench.errors import (DeviceTimeout, IllegalAddress, IllegalValue, LinkDown, ModbusException,
                          PlanError, ProtocolError, SensorFault)
from bench.interfaces import ChamberStatus

REG_MODEL = 0
REG_PV, REG_INPUT_ERROR, REG_ALARM = 100, 101, 102
REG_MODE = 200
REG_SETPOINT = 300
REG_CLEAR_INPUT_ERROR, REG_CLEAR_ALARM = 311, 312
REG_SP_LOW, REG_SP_HIGH = 602, 603
REG_DECIMALS = 606
REG_UNITS = 901
REG_RESUME, REG_HOLD, REG_TERMINATE = 1209, 1210, 1217
REG_EVENT1 = 2000
REG_PROFILE, REG_STEP, REG_EDIT = 4000, 4001, 4002
REG_STEP_TYPE, REG_RAMP_RATE, REG_TARGET, REG_END_ACTION = 4003, 4043, 4044, 4060
REG_CUR_PROFILE, REG_CUR_STEP = 4100, 4101
REG_RAMP_SP = 4122

EDIT_CREATE, EDIT_INSERT, EDIT_DELETE_PROFILE, EDIT_START = 1, 2, 3, 5
STEP_RAMP_RATE, STEP_END = 2, 5
END_HOLD = 0
MODES_PROFILE = (2, 3)

_EXC_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
              4: "slave device failure", 6: "slave device busy"}


@dataclass(frozen=True)
class _Steady:
    """Mode (200) and event 1 (2000) as read at bench time ``t`` in constant mode (see ``status``)."""

    mode: int
    power: int
    t: float


@dataclass
class _HostRamp:
    start_c: float
    target_c: float
    rate_c_per_min: float
    t0: float
    held_since: float | None = None
    held_total_s: float = 0.0
    last_written_raw: int | None = None


class WatlowF4Chamber:
    """``bench.interfaces.Chamber`` for a Watlow F4 (or F4T in F4-compatible data map)."""

    def __init__(self, config: ChamberConfig, clock: Clock | None = None) -> None:
        self.config = config
        self.clock: Clock = clock if clock is not None else RealClock()
        self.unit = config.unit_id
        self._where = f"chamber {config.transport} {config.address} unit {config.unit_id}"
        self._client = self._make_client(config)
        self._lock = threading.RLock()
        self._connected = False
        self._last_io_end = 0.0
        self._dp: int | None = None
        self._celsius = True
        self.model_number: int | None = None
        self._host_ramp: _HostRamp | None = None
        self._steady: _Steady | None = None
        self._guard: Callable[[], None] | None = None

    # ---- transport ---------------------------------------------------------------------------
    @staticmethod
    def _make_client(config: ChamberConfig):
        if config.transport == "modbus_tcp":
            host, sep, port = config.address.rpartition(":")
            if not sep or not host or not port.isdigit():
                raise LinkDown(f"chamber modbus_tcp address {config.address!r} is not 'host:port'")
            return ModbusTcpClient(host, port=int(port), timeout=config.timeout_s, retries=config.retries)
        return ModbusSerialClient(config.address, framer=FramerType.RTU, baudrate=config.baudrate,
                                  bytesize=8, parity="N", stopbits=1, timeout=config.timeout_s,
                                  retries=config.retries)

    def _pace(self) -> None:
        wait = self._last_io_end + self.config.inter_frame_delay_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)

    def _drop_connection(self) -> None:
        self._client.close()
        self._connected = False
        self._steady = None

    def _connect(self) -> None:
        if self._connected:
            return
        if not self._client.connect():
            self._client.close()
            raise LinkDown(f"{self._where}: cannot open the link")
        self._connected = True
        self._last_io_end = 0.0
        try:
            self.model_number = self._read(REG_MODEL, what="model")[0]
            dp = self._read(REG_DECIMALS, what="input 1 decimals")[0]
            if not 0 <= dp <= 3:
                raise ProtocolError(f"{self._where}: register {REG_DECIMALS} (decimals) reads {dp}, expected 0..3")
            self._dp = dp
            self._celsius = self._read(REG_UNITS, what="temperature units")[0] == 1
        except Exception:
            self._drop_connection()
            raise

    def guard_requests(self, guard: Callable[[], None] | None) -> None:
        """Call ``guard`` before every Modbus request (it raises to keep one off the wire)."""
        self._guard = guard

    def _transact(self, what: str, reg: int, call):
        """Run one Modbus transaction, mapping every failure to a ``bench.errors`` type."""
        self._pace()
        if self._guard is not None:
            self._guard()
        try:
            reply = call()
        except ModbusIOException as exc:
            self._drop_connection()
            if "No response" in str(exc):
                raise DeviceTimeout(f"{self._where}: no reply to {what} (register {reg}) within "
                                    f"{self.config.timeout_s} s x {self.config.retries + 1} tries") from None
            raise ProtocolError(f"{self._where}: bad reply to {what} (register {reg}): {exc}") from None
        except ConnectionException as exc:
            self._drop_connection()
            raise LinkDown(f"{self._where}: link lost during {what} (register {reg}): {exc}") from None
        except OSError as exc:
            self._drop_connection()
            raise LinkDown(f"{self._where}: link error during {what} (register {reg}): {exc}") from None
        finally:
            self._last_io_end = time.monotonic()
        if reply.isError():
            code = getattr(reply, "exception_code", None)
            text = f"{self._where}: {what} (register {reg}) refused with Modbus exception {code:02d}" \
                if code is not None else f"{self._where}: {what} (register {reg}) failed: {reply}"
            if code in _EXC_NAMES:
                text += f" ({_EXC_NAMES[code]})"
            if code == 2:
                raise IllegalAddress(text, code)
            if code == 3:
                raise IllegalValue(text, code)
            raise ModbusException(text, code if code is not None else -1)
        return reply

    def _read(self, reg: int, count: int = 1, *, what: str = "read") -> list[int]:
        reply = self._transact(f"read {what}", reg, lambda: self._client.read_holding_registers(
            reg, count=count, device_id=self.unit))
        regs = list(reply.registers)
        if len(regs) != count:
            raise ProtocolError(f"{self._where}: read {what} (register {reg}) returned {len(regs)} "
                                f"registers, asked {count}")
        return regs

    def _write(self, reg: int, value: int, *, what: str) -> None:
        raw = value & 0xFFFF
        self._steady = None                 # a write may change the mode or the events: read them again
        self._transact(f"write {what} = {value}", reg, lambda: self._client.write_register(
            reg, raw, device_id=self.unit))

    def _write_pair(self, reg: int, values: list[int], *, what: str) -> None:
        raws = [v & 0xFFFF for v in values]
        self._steady = None
        self._transact(f"write {what} = {values}", reg, lambda: self._client.write_registers(
            reg, raws, device_id=self.unit))

    def _op(self, fn):
        with self._lock:
            self._connect()
            return fn()

    # ---- value conversion ----------------------------------------------------------------------
    def _to_c(self, raw: int) -> float:
        signed = raw - 0x10000 if raw >= 0x8000 else raw
        value = signed * 10.0 ** -self._dp
        return value if self._celsius else (value - 32.0) * 5.0 / 9.0

    def _to_raw(self, celsius: float, what: str, reg: int) -> int:
        value = celsius if self._celsius else celsius * 9.0 / 5.0 + 32.0
        raw = round(value * 10 ** self._dp)
        if not -32768 <= raw <= 32767:
            raise IllegalValue(f"{self._where}: {what} {celsius} C does not fit register {reg} "
                               f"(int16 with {self._dp} decimals)", 3)
        return raw

    def _rate_raw(self, rate_c_per_min: float) -> int:
        per_min = rate_c_per_min if self._celsius else rate_c_per_min * 9.0 / 5.0
        return round(per_min * 10)

    # ---- Chamber protocol ----------------------------------------------------------------------
    def read_temperature(self) -> float:
        """PV (100), refused with ``SensorFault`` when 101 reports an input error."""
        def go() -> float:
            pv, err = self._read(REG_PV, 2, what="PV and input error")
            if err:
                raise SensorFault(f"{self._where}: input 1 error code {err} (register {REG_INPUT_ERROR}); "
                                  f"PV register {REG_PV} reads raw {pv}")
            return self._to_c(pv)
        return self._op(go)

    def read_setpoint(self) -> float:
        return self._op(lambda: self._to_c(self._read(REG_SETPOINT, what="set point")[0]))

    def setpoint_limits(self) -> tuple[float, float]:
        def go() -> tuple[float, float]:
            low, high = self._read(REG_SP_LOW, 2, what="set-point limits")
            return self._to_c(low), self._to_c(high)
        return self._op(go)

    def _check_in_limits(self, celsius: float, what: str) -> None:
        if not math.isfinite(celsius):
            raise IllegalValue(f"{self._where}: {what} {celsius} is not a number", 3)
        low, high = self.setpoint_limits()
        if not low <= celsius <= high:
            raise IllegalValue(f"{self._where}: {what} {celsius:.2f} C outside the controller limits "
                               f"{low:.2f}..{high:.2f} C (registers {REG_SP_LOW}/{REG_SP_HIGH})", 3)

    def set_setpoint(self, celsius: float) -> None:
        """Static set point (300); checked against 602/603 first, the controller checks again (03)."""
        def go() -> None:
            self._check_in_limits(celsius, "set point")
            self._write(REG_SETPOINT, self._to_raw(celsius, "set point", REG_SETPOINT), what="set point")
        self._op(go)

    def ramp_to(self, target_c: float, rate_c_per_min: float) -> None:
        if not (math.isfinite(rate_c_per_min) and 0.1 <= rate_c_per_min <= self.config.max_ramp_c_per_min):
            raise PlanError(f"{self._where}: ramp rate {rate_c_per_min} C/min outside 0.1.."
                            f"{self.config.max_ramp_c_per_min} C/min (config max_ramp_c_per_min)")

        def go() -> None:
            self._check_in_limits(target_c, "ramp target")
            self._stop_locked()
            if self.config.ramp_mode == "host":
                self._start_host_ramp(target_c, rate_c_per_min)
            else:
                self._start_profile_ramp(target_c, rate_c_per_min)
        self._op(go)

    def _start_profile_ramp(self, target_c: float, rate_c_per_min: float) -> None:
        target_raw = self._to_raw(target_c, "ramp target", REG_TARGET)
        rate_raw = self._rate_raw(rate_c_per_min)
        self._write(REG_PROFILE, self.config.profile_number, what="profile number")
        self._write(REG_EDIT, EDIT_DELETE_PROFILE, what="delete profile")
        self._write(REG_EDIT, EDIT_CREATE, what="create profile")
        number = self._read(REG_PROFILE, what="created profile number")[0]
        self._write_pair(REG_STEP, [1, EDIT_INSERT], what="insert step 1")
        self._write(REG_STEP_TYPE, STEP_RAMP_RATE, what="step 1 type ramp-rate")
        self._write(REG_RAMP_RATE, rate_raw, what="step 1 ramp rate x10")
        self._write(REG_TARGET, target_raw, what="step 1 target")
        self._write(REG_STEP, 2, what="step number")
        step_type = self._read(REG_STEP_TYPE, what="step 2 type")[0]
        if step_type != STEP_END:
            raise ProtocolError(f"{self._where}: profile {number} step 2 should be the end step, register "
                                f"{REG_STEP_TYPE} reads {step_type}")
        self._write(REG_END_ACTION, END_HOLD, what="end action hold")
        self._write(REG_PROFILE, number, what="profile number")
        self._write(REG_STEP, 1, what="start step")
        self._write(REG_EDIT, EDIT_START, what=f"start profile {number}")

    def _start_host_ramp(self, target_c: float, rate_c_per_min: float) -> None:
        pv, err = self._read(REG_PV, 2, what="PV and input error")
        if err:
            raise SensorFault(f"{self._where}: cannot start a ramp, input 1 error code {err} "
                              f"(register {REG_INPUT_ERROR})")
        low, high = self.setpoint_limits()
        start = min(high, max(low, self._to_c(pv)))
        self._host_ramp = _HostRamp(start, target_c, rate_c_per_min, self.clock.now())
        self._host_tick_locked()

    def _host_setpoint(self, ramp: _HostRamp) -> float:
        now = ramp.held_since if ramp.held_since is not None else self.clock.now()
        elapsed = max(0.0, now - ramp.t0 - ramp.held_total_s)
        span = ramp.target_c - ramp.start_c
        moved = ramp.rate_c_per_min / 60.0 * elapsed
        return ramp.target_c if moved >= abs(span) else ramp.start_c + math.copysign(moved, span)

    def _host_tick_locked(self) -> float | None:
        ramp = self._host_ramp
        if ramp is None:
            return None
        sp = self._host_setpoint(ramp)
        raw = self._to_raw(sp, "ramp set point", REG_SETPOINT)
        if raw != ramp.last_written_raw:
            self._write(REG_SETPOINT, raw, what="host-ramped set point")
            ramp.last_written_raw = raw
        if sp == ramp.target_c:
            self._host_ramp = None
        return sp

    def ramp_tick(self) -> float | None:
        """Host ramp mode: write the set point due now.  Returns it, or None when no host ramp runs."""
        with self._lock:
            if self._host_ramp is None:
                return None
            return self._op(self._host_tick_locked)

    @property
    def host_ramp_active(self) -> bool:
        return self._host_ramp is not None

    def hold(self) -> None:
        def go() -> None:
            if self._host_ramp is not None:
                if self._host_ramp.held_since is None:
                    self._host_ramp.held_since = self.clock.now()
                return
            self._write(REG_HOLD, 1, what="hold profile")
        self._op(go)

    def resume(self) -> None:
        def go() -> None:
            ramp = self._host_ramp
            if ramp is not None:
                if ramp.held_since is not None:
                    ramp.held_total_s += self.clock.now() - ramp.held_since
                    ramp.held_since = None
                self._host_tick_locked()
                return
            self._write(REG_RESUME, 1, what="resume profile")
        self._op(go)

    def _stop_locked(self) -> None:
        self._host_ramp = None
        mode = self._read(REG_MODE, what="mode")[0]
        if mode in MODES_PROFILE:
            ramp_raw = self._read(REG_RAMP_SP, what="ramping set point")[0]
            self._write(REG_SETPOINT, ramp_raw - 0x10000 if ramp_raw >= 0x8000 else ramp_raw,
                        what="set point = present ramping set point")
            self._write(REG_TERMINATE, 1, what="terminate profile")

    def stop(self) -> None:
        """End any ramp; the chamber keeps controlling at the set point reached."""
        self._op(self._stop_locked)

    def set_power(self, on: bool) -> None:
        self._op(lambda: self._write(REG_EVENT1, 1 if on else 0, what="event 1 (chamber power)"))

    def status(self) -> ChamberStatus:
        """PV, set point, mode, alarm, input error, chamber power and ramping set point; 200 and 2000
        are read again only when due (module docstring, "Status")."""
        def go() -> ChamberStatus:
            host_sp = self._host_tick_locked()
            pv, err, alarm = self._read(REG_PV, 3, what="PV, input error, alarm")
            now = self.clock.now()
            known = self._steady
            if known is not None and not known.t <= now < known.t + self.config.status_refresh_s:
                known = None
            mode = known.mode if known is not None else self._read(REG_MODE, what="mode")[0]
            sp = self._read(REG_SETPOINT, what="set point")[0]
            power = known.power if known is not None else self._read(REG_EVENT1, what="event 1 (chamber power)")[0]
            ramp_sp: float | None = host_sp
            if mode in MODES_PROFILE:
                ramp_sp = self._to_c(self._read(REG_RAMP_SP, what="ramping set point")[0])
                self._steady = None
            elif known is None:
                self._steady = _Steady(mode, power, now)
            return ChamberStatus(pv_c=self._to_c(pv), setpoint_c=self._to_c(sp), ramp_setpoint_c=ramp_sp,
                                 mode=mode, alarm=alarm, input_error=err, power_on=power == 1)
        return self._op(go)

    def clear_alarm(self) -> None:
        """Clear alarm 1 (312) and a latched input 1 error (311)."""
        def go() -> None:
            self._write(REG_CLEAR_ALARM, 1, what="clear alarm 1")
            self._write(REG_CLEAR_INPUT_ERROR, 1, what="clear input 1 error")
        self._op(go)

    def close(self) -> None:
        with self._lock:
            self._drop_connection()
            self._dp = None

    def __enter__(self) -> "WatlowF4Chamber":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

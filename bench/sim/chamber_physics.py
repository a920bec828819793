"""Chamber physics and F4-like controller (engineering units, degrees C, bench seconds): the air
temperature model ``ChamberModel`` with its static set point, profiles (``ProfileStep``), alarm and
sensor-fault behaviour, beside the gyro physics in ``bench.sim.physics``.  The Watlow F4 Modbus
front-end that serves it is ``bench.sim.chamber.ChamberSimulator``.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from bench.errors import IllegalValue

MODE_CONSTANT = 0
MODE_RUNNING = 2
MODE_HELD = 3

STEP_AUTOSTART, STEP_RAMP_TIME, STEP_RAMP_RATE, STEP_SOAK, STEP_JUMP, STEP_END = 0, 1, 2, 3, 4, 5
END_HOLD, END_CONTROL_OFF, END_ALL_OFF, END_IDLE = 0, 1, 2, 3

ALARM_NONE, ALARM_LOW, ALARM_HIGH = 0, 1, 2


@dataclass(frozen=True)
class ProfileStep:
    """One executable profile step in engineering units."""

    kind: int                          # STEP_RAMP_TIME / STEP_RAMP_RATE / STEP_SOAK / STEP_END
    target_c: float = 0.0              # ramp target (ramp steps)
    rate_c_per_min: float = 0.0        # ramp-rate steps
    duration_s: float = 0.0            # ramp-time and soak steps
    end_action: int = END_HOLD         # end steps
    idle_setpoint_c: float = 0.0       # end action idle


class _RunningProfile:
    def __init__(self, number: int, steps: list[ProfileStep], index: int, start_sp_c: float) -> None:
        self.number = number
        self.steps = steps
        self.index = index
        self.held = False
        self.ramp_sp_c = start_sp_c
        self.step_start_sp_c = start_sp_c
        self.step_elapsed_s = 0.0


class ChamberModel:
    """Chamber air temperature under an F4-like controller.

    Air dynamics (each sub-step of at most ``step_s`` bench seconds):
    with control on, the air relaxes towards the active set point with time constant
    ``control_tau_s`` but its rate of change is clipped to ``+heat_rate`` / ``-cool_rate`` (C/min), the
    heater/compressor capacity.  With chamber power off (event 1), control outputs off (end action)
    or a sensor fault, the air relaxes towards ``ambient_c`` with ``ambient_tau_s``.

    The active set point is the ramping profile set point (4122) while a profile runs or is held,
    else the static set point (300).  Thread-safe; getters return the state after the last
    ``advance_to``.  Commands act at the last advanced time (front-ends advance first).
    """

    def __init__(self, *, air_c: float = 23.0, setpoint_c: float | None = None, ambient_c: float = 23.0,
                 heat_rate_c_per_min: float = 5.0, cool_rate_c_per_min: float = 5.0,
                 control_tau_s: float = 30.0, ambient_tau_s: float = 1800.0,
                 setpoint_min_c: float = -70.0, setpoint_max_c: float = 180.0,
                 alarm_band_c: tuple[float, float] = (-10.0, 10.0), step_s: float = 1.0) -> None:
        if heat_rate_c_per_min <= 0 or cool_rate_c_per_min <= 0:
            raise ValueError("heating and cooling rates must be > 0 C/min")
        if control_tau_s <= 0 or ambient_tau_s <= 0 or step_s <= 0:
            raise ValueError("time constants and the integration step must be > 0 s")
        if setpoint_min_c >= setpoint_max_c:
            raise ValueError(f"set-point limits {setpoint_min_c}..{setpoint_max_c} are not increasing")
        self._lock = threading.RLock()
        self.ambient_c = float(ambient_c)
        self.heat_rate_c_per_min = float(heat_rate_c_per_min)
        self.cool_rate_c_per_min = float(cool_rate_c_per_min)
        self.control_tau_s = float(control_tau_s)
        self.ambient_tau_s = float(ambient_tau_s)
        self.step_s = float(step_s)
        self._t: float | None = None
        self._air = float(air_c)
        self._sp_min = float(setpoint_min_c)
        self._sp_max = float(setpoint_max_c)
        sp = float(air_c if setpoint_c is None else setpoint_c)
        self._check_sp(sp, "static set point")
        self._sp = sp
        self._power_on = True
        self._control_off = False
        self._profile: _RunningProfile | None = None
        self._alarm_band = (float(alarm_band_c[0]), float(alarm_band_c[1]))
        self._alarm_armed = False
        self._alarm = ALARM_NONE
        self._injected_alarm = 0
        self._sensor_fault = 0
        self._input_error = 0
        self._cal_offset = 0.0
        self._last_rate_c_per_s = 0.0

    # ---- time ----------------------------------------------------------------------------
    def advance_to(self, t_bench: float) -> None:
        with self._lock:
            if self._t is None:
                self._t = float(t_bench)
                self._update_alarms()
                return
            remaining = float(t_bench) - self._t
            while remaining > 1e-12:
                dt = min(self.step_s, remaining)
                self._advance_profile(dt)
                self._advance_air(dt)
                self._update_alarms()
                self._t += dt
                remaining -= dt

    def _active_sp(self) -> float:
        return self._profile.ramp_sp_c if self._profile is not None else self._sp

    def _controlling(self) -> bool:
        return self._power_on and not self._control_off and self._input_error == 0

    def _advance_air(self, dt: float) -> None:
        if self._controlling():
            goal, tau = self._active_sp(), self.control_tau_s
        else:
            goal, tau = self.ambient_c, self.ambient_tau_s
        change = (goal - self._air) * (1.0 - math.exp(-dt / tau))
        if self._controlling():
            change = max(-self.cool_rate_c_per_min / 60.0 * dt, min(self.heat_rate_c_per_min / 60.0 * dt, change))
        self._air += change
        self._last_rate_c_per_s = change / dt

    def _advance_profile(self, dt: float) -> None:
        prof = self._profile
        while prof is not None and not prof.held and dt > 1e-12:
            step = prof.steps[prof.index]
            if step.kind == STEP_END:
                self._finish_profile(step)
                return
            if step.kind == STEP_RAMP_RATE:
                per_s = step.rate_c_per_min / 60.0
                distance = step.target_c - prof.ramp_sp_c
                needed = abs(distance) / per_s
                if needed <= dt + 1e-9:
                    prof.ramp_sp_c = step.target_c
                    dt = max(0.0, dt - needed)
                    self._next_step(prof)
                else:
                    prof.ramp_sp_c += math.copysign(per_s * dt, distance)
                    prof.step_elapsed_s += dt
                    dt = 0.0
                prof = self._profile
                continue
            # ramp-time and soak: timed steps
            left = step.duration_s - prof.step_elapsed_s
            used = min(dt, max(left, 0.0))
            prof.step_elapsed_s += used
            dt -= used
            if step.kind == STEP_RAMP_TIME:
                frac = 1.0 if step.duration_s <= 0 else min(1.0, prof.step_elapsed_s / step.duration_s)
                prof.ramp_sp_c = prof.step_start_sp_c + (step.target_c - prof.step_start_sp_c) * frac
            if prof.step_elapsed_s >= step.duration_s - 1e-9:
                self._next_step(prof)
            prof = self._profile

    def _next_step(self, prof: _RunningProfile) -> None:
        prof.index += 1
        prof.step_elapsed_s = 0.0
        prof.step_start_sp_c = prof.ramp_sp_c
        if prof.index >= len(prof.steps):   # defensive: validated profiles always end with an end step
            self._finish_profile(ProfileStep(STEP_END))
        elif prof.steps[prof.index].kind == STEP_END:
            self._finish_profile(prof.steps[prof.index])

    def _finish_profile(self, end: ProfileStep) -> None:
        last_sp = self._profile.ramp_sp_c if self._profile is not None else self._sp
        self._profile = None
        if end.end_action == END_HOLD:
            self._sp = min(self._sp_max, max(self._sp_min, last_sp))
        elif end.end_action in (END_CONTROL_OFF, END_ALL_OFF):
            self._control_off = True
            if end.end_action == END_ALL_OFF:
                self._power_on = False          # event outputs off, event 1 = chamber power
        elif end.end_action == END_IDLE:
            self._sp = min(self._sp_max, max(self._sp_min, end.idle_setpoint_c))
            self._alarm_armed = False

    def _update_alarms(self) -> None:
        if self._sensor_fault:
            self._input_error = self._sensor_fault
        deviation = self._air - self._active_sp()
        low, high = self._alarm_band
        inside = low <= deviation <= high
        if inside:
            self._alarm_armed = True
        elif self._alarm_armed and self._alarm == ALARM_NONE:
            self._alarm = ALARM_LOW if deviation < low else ALARM_HIGH
        if self._injected_alarm:
            self._alarm = self._injected_alarm

    # ---- getters --------------------------------------------------------------------------
    @property
    def now(self) -> float | None:
        with self._lock:
            return self._t

    @property
    def air_c(self) -> float:
        """True chamber air temperature (what the gyro model should read)."""
        with self._lock:
            return self._air

    @property
    def pv_c(self) -> float:
        """Controller process value: air plus the input calibration offset (605)."""
        with self._lock:
            return self._air + self._cal_offset

    @property
    def setpoint_c(self) -> float:
        with self._lock:
            return self._sp

    @property
    def active_setpoint_c(self) -> float:
        with self._lock:
            return self._active_sp()

    @property
    def ramp_setpoint_c(self) -> float | None:
        with self._lock:
            return None if self._profile is None else self._profile.ramp_sp_c

    @property
    def mode(self) -> int:
        with self._lock:
            if self._profile is None:
                return MODE_CONSTANT
            return MODE_HELD if self._profile.held else MODE_RUNNING

    @property
    def power_on(self) -> bool:
        with self._lock:
            return self._power_on

    @property
    def control_off(self) -> bool:
        with self._lock:
            return self._control_off

    @property
    def alarm(self) -> int:
        with self._lock:
            return self._alarm

    @property
    def input_error(self) -> int:
        with self._lock:
            return self._input_error

    @property
    def setpoint_limits(self) -> tuple[float, float]:
        with self._lock:
            return self._sp_min, self._sp_max

    @property
    def alarm_band_c(self) -> tuple[float, float]:
        with self._lock:
            return self._alarm_band

    @property
    def cal_offset_c(self) -> float:
        with self._lock:
            return self._cal_offset

    @property
    def output_percent(self) -> tuple[float, float]:
        """(heat %, cool %) over the last sub-step, as fractions of the capacity."""
        with self._lock:
            rate = self._last_rate_c_per_s * 60.0
            if not self._controlling():
                return 0.0, 0.0
            heat = max(0.0, rate) / self.heat_rate_c_per_min * 100.0
            cool = max(0.0, -rate) / self.cool_rate_c_per_min * 100.0
            return min(heat, 100.0), min(cool, 100.0)

    @property
    def profile_position(self) -> tuple[int, int, int, float | None]:
        """(profile number, step number 1-based, step type, seconds left in a timed step or ramp)."""
        with self._lock:
            prof = self._profile
            if prof is None:
                return 0, 0, 0, None
            step = prof.steps[prof.index]
            if step.kind == STEP_RAMP_RATE:
                left = abs(step.target_c - prof.ramp_sp_c) / (step.rate_c_per_min / 60.0)
            elif step.kind in (STEP_RAMP_TIME, STEP_SOAK):
                left = max(0.0, step.duration_s - prof.step_elapsed_s)
            else:
                left = None
            return prof.number, prof.index + 1, step.kind, left

    # ---- commands -------------------------------------------------------------------------
    def _check_sp(self, celsius: float, what: str) -> None:
        if not self._sp_min <= celsius <= self._sp_max:
            raise IllegalValue(f"{what} {celsius:.2f} C outside the set-point limits "
                               f"{self._sp_min:.2f}..{self._sp_max:.2f} C (602/603)", code=3)

    def set_setpoint(self, celsius: float) -> None:
        with self._lock:
            self._check_sp(celsius, "static set point")
            if celsius != self._sp:
                self._alarm_armed = False
            self._sp = float(celsius)
            self._control_off = False

    def set_setpoint_limits(self, low_c: float, high_c: float) -> None:
        with self._lock:
            if low_c >= high_c:
                raise IllegalValue(f"set-point low limit {low_c:.2f} C not below high limit {high_c:.2f} C", code=3)
            self._sp_min, self._sp_max = float(low_c), float(high_c)
            self._sp = min(self._sp_max, max(self._sp_min, self._sp))

    def set_alarm_band(self, low_c: float, high_c: float) -> None:
        with self._lock:
            if not low_c <= 0.0 <= high_c:
                raise IllegalValue(f"alarm deviation band {low_c:.2f}..{high_c:.2f} C must contain 0", code=3)
            self._alarm_band = (float(low_c), float(high_c))

    def set_cal_offset(self, offset_c: float) -> None:
        with self._lock:
            self._cal_offset = float(offset_c)

    def set_power(self, on: bool) -> None:
        with self._lock:
            self._power_on = bool(on)

    def start_profile(self, number: int, steps: list[ProfileStep], start_step: int = 1) -> None:
        with self._lock:
            if not steps or steps[-1].kind != STEP_END:
                raise IllegalValue(f"profile {number} does not end with an end step", code=3)
            if not 1 <= start_step <= len(steps):
                raise IllegalValue(f"profile {number} has no step {start_step}", code=3)
            for i, step in enumerate(steps, start=1):
                if step.kind not in (STEP_RAMP_TIME, STEP_RAMP_RATE, STEP_SOAK, STEP_END):
                    raise IllegalValue(f"profile {number} step {i}: step type {step.kind} is not simulated", code=3)
                if step.kind == STEP_RAMP_RATE and step.rate_c_per_min <= 0:
                    raise IllegalValue(f"profile {number} step {i}: ramp rate must be > 0", code=3)
                if step.kind in (STEP_RAMP_TIME, STEP_RAMP_RATE):
                    self._check_sp(step.target_c, f"profile {number} step {i} target")
            prof = _RunningProfile(number, list(steps), start_step - 1, self._air + self._cal_offset)
            self._profile = prof
            self._control_off = False
            self._alarm_armed = False
            if prof.steps[prof.index].kind == STEP_END:
                self._finish_profile(prof.steps[prof.index])

    def hold_profile(self) -> None:
        with self._lock:
            if self._profile is not None:
                self._profile.held = True

    def resume_profile(self) -> None:
        with self._lock:
            if self._profile is not None:
                self._profile.held = False

    def terminate_profile(self) -> None:
        with self._lock:
            if self._profile is not None:
                self._profile = None
                self._alarm_armed = False

    @property
    def running_profile_number(self) -> int:
        with self._lock:
            return 0 if self._profile is None else self._profile.number

    def clear_alarm(self) -> None:
        with self._lock:
            if self._injected_alarm:
                return
            low, high = self._alarm_band
            if low <= self._air - self._active_sp() <= high:
                self._alarm = ALARM_NONE

    def clear_input_error(self) -> None:
        with self._lock:
            if not self._sensor_fault:
                self._input_error = 0

    # ---- fault injection --------------------------------------------------------------------
    def inject_sensor_fault(self, code: int) -> None:
        """Non-zero: the input 1 sensor is open/shorted (latches 101 = code).  0: sensor repaired."""
        with self._lock:
            self._sensor_fault = int(code)
            if code:
                self._input_error = int(code)

    def inject_alarm(self, code: int) -> None:
        """Non-zero: alarm 1 condition forced (102 = code).  0: condition removed (still latched)."""
        with self._lock:
            self._injected_alarm = int(code)
            if code:
                self._alarm = int(code)

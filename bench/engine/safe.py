"""Safe state (``BenchConfig.safe_state``) and blocking table moves.

Order: chamber (to the safe set point, or hold), turntable (rate 0 on both axes, then park),
gyro power (off / on / keep).  Each action is bounded by ``safe_state.timeout_s`` bench seconds,
logged as an event, and a failure of one action does not skip the others.
"""
from __future__ import annotations

from typing import Callable

from bench.clock import Deadline
from bench.config import BenchConfig
from bench.engine.devices import Devices
from bench.errors import DeviceError

LogFn = Callable[..., None]
POLL_S = 0.5


def angle_error(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def wait_until(clock, timeout_s: float, done: Callable[[], bool]) -> bool:
    deadline = Deadline(clock, timeout_s)
    while True:
        if done():
            return True
        if deadline.passed():
            return False
        clock.sleep(POLL_S)


def table_at(devices: Devices, config: BenchConfig, outer: float, inner: float) -> bool:
    geo = config.turntable.geometry
    tol = config.turntable.position_tolerance_deg
    a = devices.turntable.read(geo.outer_axis_number)
    b = devices.turntable.read(geo.inner_axis_number)
    return (angle_error(a.position_deg, outer) <= tol and angle_error(b.position_deg, inner) <= tol
            and abs(a.rate_dps) < 0.1 and abs(b.rate_dps) < 0.1)


def command_table_move(devices: Devices, config: BenchConfig, outer: float, inner: float) -> None:
    """Command both axes so they travel together: drivers whose ``move_to`` takes ``wait=False``
    return at once (the caller polls positions); a plain Protocol ``move_to`` may block per axis."""
    geo = config.turntable.geometry
    for axis, deg in ((geo.outer_axis_number, outer), (geo.inner_axis_number, inner)):
        try:
            devices.turntable.move_to(axis, deg, wait=False)  # type: ignore[call-arg]
        except TypeError:
            devices.turntable.move_to(axis, deg)


def move_table_and_wait(devices: Devices, clock, config: BenchConfig, outer: float, inner: float,
                        timeout_s: float) -> bool:
    command_table_move(devices, config, outer, inner)
    return wait_until(clock, timeout_s, lambda: table_at(devices, config, outer, inner))


def enter_safe_state(devices: Devices, clock, config: BenchConfig, ramp_active: bool, log: LogFn) -> bool:
    """Put the bench in the configured safe state; True when every action succeeded in time."""
    safe = config.safe_state
    geo = config.turntable.geometry
    all_ok = True

    def attempt(kind: str, what: str, action: Callable[[], bool]) -> None:
        nonlocal all_ok
        try:
            ok = action()
        except DeviceError as exc:
            all_ok = False
            log("error", kind, f"safe state: {what} failed: {exc}")
            return
        if ok:
            log("info", kind, f"safe state: {what}")
        else:
            all_ok = False
            log("error", kind, f"safe state: {what} not confirmed within {safe.timeout_s:g} s")

    def chamber() -> bool:
        if safe.chamber == "hold":
            if ramp_active:
                devices.chamber.hold()
            return True
        if ramp_active:
            devices.chamber.stop()
        devices.chamber.set_setpoint(safe.chamber_setpoint_c)
        return wait_until(clock, safe.timeout_s,
                          lambda: abs(devices.chamber.read_setpoint() - safe.chamber_setpoint_c) < 0.05)

    def table() -> bool:
        for axis in (geo.outer_axis_number, geo.inner_axis_number):
            devices.turntable.rate(axis, 0.0)
        stopped = wait_until(clock, safe.timeout_s, lambda: all(
            abs(devices.turntable.read(a).rate_dps) < 0.1 for a in (geo.outer_axis_number, geo.inner_axis_number)))
        if not stopped:
            return False
        return move_table_and_wait(devices, clock, config, safe.park_outer_deg, safe.park_inner_deg,
                                   safe.timeout_s)

    def power() -> bool:
        if safe.gyro_power == "keep":
            return True
        on = safe.gyro_power == "on"
        devices.psu.output(on)
        return wait_until(clock, safe.timeout_s, lambda: devices.psu.output_state() == on)

    chamber_what = (f"chamber set point {safe.chamber_setpoint_c:g} C" if safe.chamber == "setpoint"
                    else "chamber held")
    attempt("safe_chamber", chamber_what, chamber)
    attempt("safe_table", f"turntable rate 0 and parked at ({safe.park_outer_deg:g}, {safe.park_inner_deg:g}) deg",
            table)
    attempt("safe_power", f"gyro power {safe.gyro_power}", power)
    return all_ok

"""Simulated two-axis rate/position table with an Acutronic ACUTROL3000 "ACL" front-end.

Protocol facts used (reference/device-protocols.md section 2.1, from Acutronic TM-8004 rev C,
TM-9384C, TM-9411 and public drivers):

- SCPI-like tree, case-insensitive; a keyword may be shortened to any prefix of its full name that
  is at least as long as its short form (the capitals in the manual's spelling: ``:Demand:Position``
  -> ``:D:P`` = ``:Dem:Pos`` = ``:DEMAND:POSITION``).
- One space between header and arguments, commas between arguments; ``:D:P,3,10.5`` is an error.
- ``;`` chains commands at the same tree level (a relative header continues from the parent of the
  previous command), ``;:`` returns to the root; common ``*`` commands do not change the level.
- Numbers NRf in; NR2 out (``10.0001``), never a leading ``+``.
- Axis argument 1..n; ``ALL`` allowed for commands but not for queries.
- ``*IDN?`` -> ``Acutronic R&D USA,Acutrol3000,0,A8800-001-01.000-a``.
- ``:Read:...`` queries accept the header without ``?`` (ACT2000 compatibility).
- On serial/TCP every command gets a reply: data for queries, ``OK`` otherwise.

Simulator choices where the manual is not public (documented assumptions):

- Chained queries reply with one line, the data joined by ``;`` (``10.0001;44.1250``); a line
  without queries replies ``OK``.  Processing stops at the first failing command and the reply is
  ``ERR <code>,<message>`` (SCPI error numbers: -102 syntax, -104 data type, -108 parameter not
  allowed, -109 missing parameter, -113 undefined header, -221 settings conflict, -222 data out of
  range, -224 illegal parameter value).
- ``:Mode? n`` replies ``P``, ``R`` or ``O`` (position, rate, off); ``:Interlock? n`` replies
  ``Closed``, ``Open`` or ``Fault``.
- Positions are reported wrapped to (-180, 180] deg; both axes are continuous (slip rings) and a
  position move takes the shorter way round.
- Framing "line": reply text + ``\\r\\n``.  Framing "acutrol_header" (ASSUMED layout, the real one
  is only known to be an 8-byte prefix with an error code and message length, TM-8004 section 2):
  ``struct "<iI"`` = int32 little-endian error code (0 = success, else the negative code above),
  uint32 little-endian length of the data that follows; then the data (``OK``, query data, or the
  error message) with no terminator.  Little-endian because ACL binary data is LSB first.

Physics (``TableModel``): per axis, acceleration-limited motion with a per-mode rate limit.  Rate
mode ramps to the rate demand at the acceleration; position mode follows a braking curve
``v = sign(e) * min(v_limit, sqrt(2 * 0.9 a |e|))`` ending in a linear capture zone; off mode and an open interlock brake to zero
rate.  Motion happens only with the interlock closed.  Integrated with a fixed sub-step (2 ms)
during transients; steady states (holding, constant rate) are advanced in closed form so long
bench-time gaps cost nothing.
"""
from __future__ import annotations

import math
import re
import struct
import threading
from dataclasses import dataclass, field
from typing import Any, Callable

from bench.clock import Clock
from bench.sim.lineserver import LineServer
from bench.sim.locked import locked_all_axes_reader, locked_axis_reader, locked_property

IDN = "Acutronic R&D USA,Acutrol3000,0,A8800-001-01.000-a"

ERROR_TEXT = {
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -221: "Settings conflict",
    -222: "Data out of range",
    -224: "Illegal parameter value",
}

MODE_LETTERS = {"P": "Position", "R": "Rate", "O": "Off"}

# Position-loop shape: brake on sqrt(2*0.9*a*|e|) (10 % margin so the acceleration limit is never
# saturated on the way in -> no overshoot), then a linear capture zone v = 50/s * e, and snap to
# the demand once within 1e-6 deg and 1e-4 deg/s (far below the 4-decimal readback).
BRAKING_FRACTION = 0.9
CAPTURE_GAIN = 50.0
SETTLE_POSITION_DEG = 1e-6
SETTLE_RATE_DPS = 1e-4


class AclError(Exception):
    """A command the controller refuses (becomes ``ERR <code>,<message>``)."""

    def __init__(self, code: int, detail: str = "") -> None:
        self.code = code
        self.message = ERROR_TEXT.get(code, "Error") + (f": {detail}" if detail else "")
        super().__init__(f"{code},{self.message}")


def wrap180(deg: float) -> float:
    """Angle in (-180, 180]."""
    w = -((-deg + 180.0) % 360.0 - 180.0)
    return 180.0 if w == -180.0 else w


# ---------------------------------------------------------------------------------------------
# physics
# ---------------------------------------------------------------------------------------------
@dataclass
class _Axis:
    number: int
    max_rate: float
    max_accel: float
    position: float = 0.0
    rate: float = 0.0
    acceleration: float = 0.0
    mode: str = "O"                  # P / R / O
    interlock: str = "Open"          # Closed / Open / Fault
    position_demand: float = 0.0
    rate_demand: float = 0.0
    accel_demand: float = 50.0
    rate_limit: dict[str, float] = field(default_factory=dict)
    accel_limit: dict[str, float] = field(default_factory=dict)
    fault_reason: str = ""

    def accel(self) -> float:
        return min(self.accel_demand, self.accel_limit.get(self.mode, self.max_accel), self.max_accel)

    def target_rate(self) -> float:
        if self.interlock != "Closed" or self.mode == "O":
            return 0.0
        if self.mode == "R":
            return self.rate_demand
        err = wrap180(self.position_demand - self.position)
        v_lim = self.rate_limit.get("P", self.max_rate)
        brake = BRAKING_FRACTION * self.accel()
        mag = abs(err)
        if mag > 2.0 * brake / CAPTURE_GAIN ** 2:
            v = math.sqrt(2.0 * brake * mag)      # braking curve
        else:
            v = CAPTURE_GAIN * mag                # linear capture zone (continuous at the join)
        return math.copysign(min(v_lim, v), err)

    def steady(self) -> bool:
        if self.rate != self.target_rate():
            return False
        if self.interlock == "Closed" and self.mode == "P":
            return self.rate == 0.0 and self.position == self.position_demand
        return True

    def step(self, dt: float) -> None:
        a = self.accel()
        target = self.target_rate()
        if abs(target - self.rate) <= a * dt:
            dv, new_rate = target - self.rate, target       # reach the target rate exactly
        else:
            dv = math.copysign(a * dt, target - self.rate)
            new_rate = self.rate + dv
        self.position = wrap180(self.position + 0.5 * (self.rate + new_rate) * dt)
        self.acceleration = dv / dt
        self.rate = new_rate
        if self.interlock == "Closed" and self.mode == "P":
            err = wrap180(self.position_demand - self.position)
            if abs(err) <= SETTLE_POSITION_DEG and abs(self.rate) <= SETTLE_RATE_DPS:
                self.position, self.rate, self.acceleration = self.position_demand, 0.0, 0.0
        elif self.rate == 0.0 and target == 0.0:
            self.acceleration = 0.0

    def advance(self, duration: float, dt: float) -> None:
        """``step`` by ``dt`` until ``duration`` has passed, or until ``steady``, then coast the rest.

        The same arithmetic as ``steady`` / ``step`` in the same order (so the same floats), with what
        cannot change during the call (mode, interlock, demands, limits) read once: a move runs this
        loop hundreds of times a bench second, on the bench and on its look-ahead copies."""
        left = duration
        closed = self.interlock == "Closed"
        mode = self.mode
        fixed = 0.0 if not closed or mode == "O" else (self.rate_demand if mode == "R" else None)
        holds = closed and mode == "P"
        a = self.accel()
        v_lim = self.rate_limit.get("P", self.max_rate)
        brake = BRAKING_FRACTION * a
        zone = 2.0 * brake / CAPTURE_GAIN ** 2
        demand = self.position_demand
        position, rate, acceleration = self.position, self.rate, self.acceleration
        while left > 1e-12:
            if fixed is not None:
                target = fixed
            else:
                err = wrap180(demand - position)
                mag = abs(err)
                v = math.sqrt(2.0 * brake * mag) if mag > zone else CAPTURE_GAIN * mag
                target = math.copysign(min(v_lim, v), err)
            if rate == target and (not holds or (rate == 0.0 and position == demand)):     # steady
                self.position = wrap180(position + rate * left)
                self.rate = rate
                self.acceleration = 0.0
                return
            h = min(dt, left)
            if abs(target - rate) <= a * h:
                dv, new_rate = target - rate, target
            else:
                dv = math.copysign(a * h, target - rate)
                new_rate = rate + dv
            position = wrap180(position + 0.5 * (rate + new_rate) * h)
            acceleration = dv / h
            rate = new_rate
            if holds:
                if abs(wrap180(demand - position)) <= SETTLE_POSITION_DEG and abs(rate) <= SETTLE_RATE_DPS:
                    position, rate, acceleration = demand, 0.0, 0.0
            elif rate == 0.0 and target == 0.0:
                acceleration = 0.0
            left -= h
        self.position, self.rate, self.acceleration = position, rate, acceleration


class TableModel:
    """Two (or n) axis table physics.  Thread-safe; advanced lazily with ``advance_to``.

    Hardware limits ``max_rate_dps`` / ``max_accel_dps2`` bound what ``:Limit:...`` and demands
    may set.  Initial per-mode limits are ``rate_limit_dps`` / ``accel_dps2``.
    """

    def __init__(self, axes: int = 2, *, max_rate_dps: float = 500.0, max_accel_dps2: float = 300.0,
                 rate_limit_dps: float = 100.0, accel_dps2: float = 50.0, step_s: float = 0.002) -> None:
        if axes < 1:
            raise ValueError(f"TableModel: axes must be >= 1, got {axes}")
        if not (0 < rate_limit_dps <= max_rate_dps and 0 < accel_dps2 <= max_accel_dps2):
            raise ValueError("TableModel: need 0 < rate_limit <= max_rate and 0 < accel <= max_accel")
        self._lock = threading.RLock()
        self._t: float | None = None
        self.step_s = step_s
        self._axes = [
            _Axis(number=n, max_rate=max_rate_dps, max_accel=max_accel_dps2, accel_demand=accel_dps2,
                  rate_limit={"P": rate_limit_dps, "R": rate_limit_dps},
                  accel_limit={"P": max_accel_dps2, "R": max_accel_dps2, "O": max_accel_dps2})
            for n in range(1, axes + 1)
        ]

    # time ----------------------------------------------------------------------------------------
    def advance_to(self, t_bench: float) -> None:
        with self._lock:
            if self._t is None:
                self._t = float(t_bench)
                return
            if t_bench <= self._t:
                return
            duration = t_bench - self._t
            for axis in self._axes:
                axis.advance(duration, self.step_s)
            self._t = float(t_bench)

    time = locked_property("_t", "Bench time of the last ``advance_to`` (s); None before the first.")

    # getters -----------------------------------------------------------------------------------
    @property
    def axes(self) -> int:
        return len(self._axes)

    angles = locked_all_axes_reader("position")               # deg, per axis
    rates = locked_all_axes_reader("rate")                    # deg/s
    accelerations = locked_all_axes_reader("acceleration")    # deg/s^2
    mode = locked_axis_reader("mode")
    interlock = locked_axis_reader("interlock")
    position_demand = locked_axis_reader("position_demand")
    rate_demand = locked_axis_reader("rate_demand")
    acceleration_demand = locked_axis_reader("accel_demand")

    def rate_limit(self, mode: str, axis: int) -> float:
        with self._lock:
            return self._axis(axis).rate_limit[self._limit_mode(mode)]

    def accel_limit(self, mode: str, axis: int) -> float:
        with self._lock:
            return self._axis(axis).accel_limit[self._limit_mode(mode)]

    # commands (raise AclError) -------------------------------------------------------------------
    def set_mode(self, axis: int, mode: str) -> None:
        with self._lock:
            ax = self._axis(axis)
            if mode not in MODE_LETTERS:
                raise AclError(-224, f"mode {mode!r}")
            if mode != "O" and ax.interlock != "Closed":
                raise AclError(-221, f"axis {axis} interlock is {ax.interlock.lower()}; close it before "
                                     f"{MODE_LETTERS[mode].lower()} mode")
            ax.mode = mode

    def set_position_demand(self, axis: int, deg: float) -> None:
        with self._lock:
            self._axis(axis).position_demand = wrap180(self._finite(deg))

    def add_position_demand(self, axis: int, delta: float) -> None:
        with self._lock:
            ax = self._axis(axis)
            ax.position_demand = wrap180(ax.position_demand + self._finite(delta))

    def set_rate_demand(self, axis: int, dps: float) -> None:
        with self._lock:
            ax = self._axis(axis)
            lim = ax.rate_limit["R"]
            if abs(self._finite(dps)) > lim:
                raise AclError(-222, f"rate {dps:g} deg/s beyond the rate-mode limit {lim:g} on axis {axis}")
            ax.rate_demand = float(dps)

    def set_acceleration_demand(self, axis: int, dps2: float) -> None:
        with self._lock:
            ax = self._axis(axis)
            if not 0 < self._finite(dps2) <= ax.max_accel:
                raise AclError(-222, f"acceleration {dps2:g} outside (0, {ax.max_accel:g}] on axis {axis}")
            ax.accel_demand = float(dps2)

    def set_rate_limit(self, mode: str, axis: int, dps: float) -> None:
        with self._lock:
            ax = self._axis(axis)
            if not 0 < self._finite(dps) <= ax.max_rate:
                raise AclError(-222, f"rate limit {dps:g} outside (0, {ax.max_rate:g}] on axis {axis}")
            key = self._limit_mode(mode)
            ax.rate_limit[key] = float(dps)
            if key == "R" and abs(ax.rate_demand) > dps:
                ax.rate_demand = math.copysign(dps, ax.rate_demand)

    def set_accel_limit(self, mode: str, axis: int, dps2: float) -> None:
        with self._lock:
            ax = self._axis(axis)
            if not 0 < self._finite(dps2) <= ax.max_accel:
                raise AclError(-222, f"acceleration limit {dps2:g} outside (0, {ax.max_accel:g}] on axis {axis}")
            ax.accel_limit[self._limit_mode(mode)] = float(dps2)

    def interlock_close(self, axis: int) -> None:
        with self._lock:
            ax = self._axis(axis)
            if ax.interlock == "Fault":
                raise AclError(-221, f"axis {axis} is in fault ({ax.fault_reason}); :Interlock:Reset first")
            if ax.interlock != "Closed":
                ax.interlock = "Closed"
                ax.mode = "O"
                ax.position_demand = ax.position   # servo comes up holding where it is
                ax.rate_demand = 0.0

    def interlock_open(self, axis: int) -> None:
        with self._lock:
            ax = self._axis(axis)
            if ax.interlock == "Closed":
                ax.interlock = "Open"
            ax.mode = "O"

    def interlock_reset(self) -> None:
        with self._lock:
            for ax in self._axes:
                if ax.interlock == "Fault":
                    ax.interlock, ax.fault_reason = "Open", ""

    def inject_fault(self, axis: int, reason: str = "amplifier fault") -> None:
        """Simulate a hardware fault: servo drops out, the axis brakes, interlock reads Fault."""
        with self._lock:
            ax = self._axis(axis)
            ax.interlock, ax.fault_reason, ax.mode = "Fault", reason, "O"

    # helpers -----------------------------------------------------------------------------------
    def _axis(self, axis: int) -> _Axis:
        if not isinstance(axis, int) or not 1 <= axis <= len(self._axes):
            raise AclError(-222, f"axis {axis} (this table has axes 1..{len(self._axes)})")
        return self._axes[axis - 1]

    @staticmethod
    def _limit_mode(mode: str) -> str:
        key = mode[:1].upper() if mode else ""
        if key not in ("P", "R") or not ("POSITION".startswith(mode.upper()) or "RATE".startswith(mode.upper())):
            raise AclError(-224, f"limit mode {mode!r} (use P or R)")
        return key

    @staticmethod
    def _finite(value: float) -> float:
        if not math.isfinite(value):
            raise AclError(-222, f"value {value!r}")
        return float(value)


# ---------------------------------------------------------------------------------------------
# ACL command tree
# ---------------------------------------------------------------------------------------------
Setter = Callable[["TableModel", list[str]], None]
Getter = Callable[["TableModel", list[str]], str]


@dataclass
class Node:
    name: str                       # full keyword, e.g. "Position"
    short: str                      # minimum abbreviation (the manual's capitals), e.g. "P"
    children: list["Node"] = field(default_factory=list)
    setter: Setter | None = None
    getter: Getter | None = None
    query_mark_optional: bool = False   # :Read:... without "?" is still a query
    parent: "Node | None" = None

    def matches(self, token: str) -> bool:
        return len(token) >= len(self.short) and self.name.lower().startswith(token.lower())

    def child(self, token: str) -> "Node | None":
        for node in self.children:
            if node.matches(token):
                return node
        return None


_NRF = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_KEYWORD = re.compile(r"[A-Za-z][A-Za-z0-9]*")


def nr2(value: float) -> str:
    text = f"{value:.4f}"
    return "0.0000" if text == "-0.0000" else text


def _number(arg: str, what: str) -> float:
    if not _NRF.fullmatch(arg):
        raise AclError(-104, f"{what} {arg!r} is not a number")
    return float(arg)


def _axes(model: TableModel, arg: str, *, allow_all: bool) -> list[int]:
    if arg.upper() == "ALL":
        if not allow_all:
            raise AclError(-224, "ALL is not allowed in a query")
        return list(range(1, model.axes + 1))
    if not re.fullmatch(r"[+]?\d+", arg):
        raise AclError(-104, f"axis {arg!r} is not an axis number")
    axis = int(arg)
    if not 1 <= axis <= model.axes:
        raise AclError(-222, f"axis {axis} (this table has axes 1..{model.axes})")
    return [axis]


def _count(args: list[str], n: int, header: str) -> None:
    if len(args) < n:
        raise AclError(-109, f"{header} needs {n} argument(s), got {len(args)}")
    if len(args) > n:
        raise AclError(-108, f"{header} takes {n} argument(s), got {len(args)}")


def _mode_word(word: str) -> str:
    for letter, name in MODE_LETTERS.items():
        if word and name.lower().startswith(word.lower()):
            return letter
    raise AclError(-224, f"mode {word!r} (supported: Position, Rate, Off)")


def _axis_setter(action: Callable[[TableModel, int], None], name: str) -> Setter:
    def run(model: TableModel, args: list[str]) -> None:
        _count(args, 1, name)
        for axis in _axes(model, args[0], allow_all=True):
            action(model, axis)
    return run


def _axis_value_setter(action: Callable[[TableModel, int, float], None], name: str) -> Setter:
    def run(model: TableModel, args: list[str]) -> None:
        _count(args, 2, name)
        value = _number(args[1], f"{name} value")
        for axis in _axes(model, args[0], allow_all=True):
            action(model, axis, value)
    return run


def _axis_getter(read: Callable[[TableModel, int], str], name: str) -> Getter:
    def run(model: TableModel, args: list[str]) -> str:
        _count(args, 1, name)
        return read(model, _axes(model, args[0], allow_all=False)[0])
    return run


def _limit_setter(action: Callable[[TableModel, str, int, float], None], name: str) -> Setter:
    def run(model: TableModel, args: list[str]) -> None:
        _count(args, 3, name)
        value = _number(args[2], f"{name} value")
        for axis in _axes(model, args[1], allow_all=True):
            action(model, args[0], axis, value)
    return run


def _limit_getter(read: Callable[[TableModel, str, int], float], name: str) -> Getter:
    def run(model: TableModel, args: list[str]) -> str:
        _count(args, 2, name)
        return nr2(read(model, args[0], _axes(model, args[1], allow_all=False)[0]))
    return run


def _mode_setter(model: TableModel, args: list[str]) -> None:
    _count(args, 2, ":Mode")
    mode = _mode_word(args[1])
    for axis in _axes(model, args[0], allow_all=True):
        model.set_mode(axis, mode)


def _interlock_reset(model: TableModel, args: list[str]) -> None:
    if len(args) > 1:
        raise AclError(-108, f":Interlock:Reset takes at most one argument, got {len(args)}")
    if args:
        _axes(model, args[0], allow_all=True)   # validated; the reset acts on all axes
    model.interlock_reset()


def _lockout(model: TableModel, args: list[str]) -> None:
    _count(args, 1, ":Utility:Lockout")
    if args[0].upper() not in ("ON", "OFF", "1", "0"):
        raise AclError(-224, f"lockout {args[0]!r} (use ON or OFF)")


def _error_text(model: TableModel, args: list[str]) -> str:
    _count(args, 1, ":Query:Error?")
    if not re.fullmatch(r"[+-]?\d+", args[0]):
        raise AclError(-104, f"error code {args[0]!r}")
    return ERROR_TEXT.get(int(args[0]), "Unknown error")


def build_tree() -> Node:
    def n(name: str, short: str, *children: Node, **kw: Any) -> Node:
        node = Node(name, short, list(children), **kw)
        for c in children:
            c.parent = node
        return node

    pos = lambda v: nr2(v)  # noqa: E731
    root = n(
        "", "",
        n("Mode", "M",
          n("Position", "P", setter=_axis_setter(lambda m, a: m.set_mode(a, "P"), ":Mode:Position")),
          n("Rate", "R", setter=_axis_setter(lambda m, a: m.set_mode(a, "R"), ":Mode:Rate")),
          n("Off", "O", setter=_axis_setter(lambda m, a: m.set_mode(a, "O"), ":Mode:Off")),
          setter=_mode_setter, getter=_axis_getter(lambda m, a: m.mode(a), ":Mode?")),
        n("Demand", "D",
          n("Position", "P", setter=_axis_value_setter(TableModel.set_position_demand, ":Demand:Position"),
            getter=_axis_getter(lambda m, a: pos(m.position_demand(a)), ":Demand:Position?")),
          n("Rate", "R", setter=_axis_value_setter(TableModel.set_rate_demand, ":Demand:Rate"),
            getter=_axis_getter(lambda m, a: pos(m.rate_demand(a)), ":Demand:Rate?")),
          n("Acceleration", "A",
            setter=_axis_value_setter(TableModel.set_acceleration_demand, ":Demand:Acceleration"),
            getter=_axis_getter(lambda m, a: pos(m.acceleration_demand(a)), ":Demand:Acceleration?")),
          n("Deltaposition", "DE",
            setter=_axis_value_setter(TableModel.add_position_demand, ":Demand:Deltaposition"))),
        n("Read", "R",
          n("Position", "P", getter=_axis_getter(lambda m, a: pos(m.angles()[a - 1]), ":Read:Position?"),
            query_mark_optional=True),
          n("Rate", "R", getter=_axis_getter(lambda m, a: pos(m.rates()[a - 1]), ":Read:Rate?"),
            query_mark_optional=True),
          n("Acceleration", "A",
            getter=_axis_getter(lambda m, a: pos(m.accelerations()[a - 1]), ":Read:Acceleration?"),
            query_mark_optional=True)),
        n("Limit", "L",
          n("Rate", "R", setter=_limit_setter(TableModel.set_rate_limit, ":Limit:Rate"),
            getter=_limit_getter(TableModel.rate_limit, ":Limit:Rate?")),
          n("Acceleration", "A", setter=_limit_setter(TableModel.set_accel_limit, ":Limit:Acceleration"),
            getter=_limit_getter(TableModel.accel_limit, ":Limit:Acceleration?"))),
        n("Interlock", "I",
          n("Close", "C", setter=_axis_setter(TableModel.interlock_close, ":Interlock:Close")),
          n("Open", "O", setter=_axis_setter(TableModel.interlock_open, ":Interlock:Open")),
          n("Reset", "R", setter=_interlock_reset),
          getter=_axis_getter(lambda m, a: m.interlock(a), ":Interlock?")),
        n("Utility", "U", n("Lockout", "L", setter=_lockout)),
        n("Query", "Q", n("Error", "E", getter=_error_text)),
    )
    return root


class AclInterpreter:
    """Executes ACL program messages (one line) against a ``TableModel``.

    ``execute(line, session)`` returns ``(error_code, text)``: ``(0, "OK")``, ``(0, "1.0;2.0")`` or
    ``(code, message)`` for the first failing command.
    """

    def __init__(self, model: TableModel) -> None:
        self.model = model
        self.root = build_tree()

    def new_session(self) -> dict[str, Node]:
        return {"path": self.root}

    def execute(self, line: str, session: dict[str, Node]) -> tuple[int, str]:
        outputs: list[str] = []
        try:
            for unit in line.split(";"):
                unit = unit.strip()
                if not unit:
                    continue
                result = self._unit(unit, session)
                if result is not None:
                    outputs.append(result)
        except AclError as exc:
            return exc.code, exc.message
        return 0, (";".join(outputs) if outputs else "OK")

    def _unit(self, unit: str, session: dict[str, Node]) -> str | None:
        parts = unit.split(None, 1)
        header = parts[0]
        args = [] if len(parts) == 1 else [a.strip() for a in parts[1].split(",")]
        if any(a == "" for a in args):
            raise AclError(-109, f"empty argument in {unit!r}")
        if header.startswith("*"):
            return self._common(header, args)
        is_query = header.endswith("?")
        body = header[:-1] if is_query else header
        absolute = body.startswith(":")
        tokens = body[1:].split(":") if absolute else body.split(":")
        for token in tokens:
            if not _KEYWORD.fullmatch(token):
                bad = next((ch for ch in token if not ch.isalnum()), None)
                hint = " (a space must separate the header from its arguments)" if bad == "," else ""
                raise AclError(-102, f"bad header {header!r}{hint}")
        node = self.root if absolute else session["path"]
        for token in tokens:
            found = node.child(token)
            if found is None:
                raise AclError(-113, f"{token!r} in {header!r}")
            node = found
        session["path"] = node.parent or self.root
        if is_query or (node.setter is None and node.query_mark_optional):
            if node.getter is None:
                raise AclError(-113, f"{header!r} has no query form")
            return node.getter(self.model, args)
        if node.setter is None:
            raise AclError(-113, f"{header!r} is query-only" if node.getter else f"{header!r} is incomplete")
        node.setter(self.model, args)
        return None

    @staticmethod
    def _common(header: str, args: list[str]) -> str | None:
        upper = header.upper()
        if args:
            raise AclError(-108, f"{header} takes no arguments")
        if upper == "*IDN?":
            return IDN
        if upper == "*OPC?":
            return "1"
        if upper in ("*CLS", "*OPC"):
            return None
        raise AclError(-113, f"common command {header!r}")


class TurntableSimulator(LineServer):
    """ACL over TCP (``socket://127.0.0.1:N``).  Requests end with ``\\n`` (``\\r\\n`` accepted).

    ``framing``: "line" (reply + ``\\r\\n``) or "acutrol_header" (assumed 8-byte header, see module
    docstring).  The model is advanced to ``clock.now()`` before each request line is executed.
    """

    name = "acutrol"

    def __init__(self, model: TableModel, clock: Clock, framing: str = "line", host: str = "127.0.0.1",
                 port: int = 0) -> None:
        if framing not in ("line", "acutrol_header"):
            raise ValueError(f"turntable simulator: unknown framing {framing!r} (line, acutrol_header)")
        super().__init__(host, port, request_terminator=b"\n",
                         reply_terminator=b"\r\n" if framing == "line" else b"")
        self.model = model
        self.clock = clock
        self.framing = framing
        self.interpreter = AclInterpreter(model)
        self.lines_handled = 0

    def new_session(self) -> dict[str, Node]:
        return self.interpreter.new_session()

    def handle_line(self, session: Any, line: bytes) -> bytes | None:
        self.model.advance_to(self.clock.now())
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            code, reply = -102, ERROR_TEXT[-102] + ": non-ASCII bytes in command"
        else:
            code, reply = self.interpreter.execute(text, session)
        self.lines_handled += 1
        return encode_reply(code, reply, self.framing)


def encode_reply(code: int, text: str, framing: str) -> bytes:
    if framing == "line":
        return (f"ERR {code},{text}" if code else text).encode("ascii") + b"\r\n"
    data = text.encode("ascii")
    return struct.pack("<iI", code, len(data)) + data

"""Simulated bench power supply for the gyro: SCPI over a line server.

SCPI facts used (IEEE 488.2 / SCPI-1999; typical of Keysight E36xx, Rigol DP800, R&S HMP):

- Keywords have a short form (the capitals: ``VOLTage`` -> ``VOLT``) and a long form; either is
  accepted, case-insensitively, nothing in between.  Optional nodes in brackets
  (``[SOURce:]VOLTage[:LEVel][:IMMediate][:AMPLitude]``) may be left out.
- ``;`` separates commands; a header without a leading ``:`` continues from the node of the
  previous command; ``*`` common commands do not change it.
- Only queries produce output; a line with several queries returns one line, results joined by
  ``;``, terminated by ``\\n``.  Settings produce nothing.  Errors go to the error queue, read with
  ``SYSTem:ERRor[:NEXT]?`` -> ``-113,"Undefined header"`` / ``0,"No error"`` (queue of 20; overflow
  replaces the newest entry with ``-350,"Queue overflow"``).  A failing query produces no output.
- Numbers: NRf in, with an optional unit suffix V, mV, A, mA; NR3 out (``2.800000E+01``);
  ``OUTPut?`` -> ``1`` / ``0``.

Physics (``PsuModel``): constant-voltage / constant-current source into a load made of a resistor
in parallel with a constant-current sink (the gyro electronics).  CV while the load current at the
set voltage stays under the current limit, else CC at the limit with the voltage the load allows.
``on_since`` records the bench time the output was switched on, for the gyro warm-up model.
"""
from __future__ import annotations

import math
import random
import re
import threading
from collections import deque
from typing import Any, Callable

from bench.clock import Clock
from bench.sim.lineserver import LineServer
from bench.sim.locked import locked_property

DEFAULT_IDN = "Bench Simulator,SIM-PSU-60-5,SN000001,1.0"

SCPI_ERRORS = {
    0: "No error",
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -222: "Data out of range",
    -350: "Queue overflow",
}


class ScpiError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f'{code},"{SCPI_ERRORS[code]}"')
        self.code = code


# ---------------------------------------------------------------------------------------------
# physics
# ---------------------------------------------------------------------------------------------
class PsuModel:
    """One-channel CV/CC supply.  Thread-safe; ``advance_to`` only moves the model clock (the
    electrical state is static between commands; the output settles instantly on the bench scale).
    """

    def __init__(self, *, max_voltage_v: float = 60.0, max_current_a: float = 5.0, load_ohm: float = 56.0,
                 load_current_a: float = 0.0, noise_v: float = 0.0, noise_a: float = 0.0, seed: int = 7) -> None:
        self._lock = threading.RLock()
        self.max_voltage_v = max_voltage_v
        self.max_current_a = max_current_a
        self._t: float | None = None
        self._output = False
        self._on_since: float | None = None
        self._voltage = 0.0
        self._current_limit = min(1.0, max_current_a)
        self._load_ohm = load_ohm
        self._load_current = load_current_a
        self._noise_v, self._noise_a = noise_v, noise_a
        self._rng = random.Random(seed)

    def advance_to(self, t_bench: float) -> None:
        with self._lock:
            if self._t is None or t_bench > self._t:
                self._t = float(t_bench)

    # getters -------------------------------------------------------------------------------------
    output_on = locked_property("_output", "True while the output is on.")
    on_since = locked_property("_on_since", "Bench time the output was last switched on; ``None`` while off.")
    voltage_setting = locked_property("_voltage", "Programmed voltage (V).")
    current_limit = locked_property("_current_limit", "Programmed current limit (A).")

    def regulation(self) -> str:
        """``OFF``, ``CV`` or ``CC``."""
        with self._lock:
            if not self._output:
                return "OFF"
            return "CV" if self._load_at(self._voltage) <= self._current_limit else "CC"

    def output_voltage(self) -> float:
        """True terminal voltage (no measurement noise)."""
        with self._lock:
            return self._operating_point()[0]

    def output_current(self) -> float:
        with self._lock:
            return self._operating_point()[1]

    def measure_voltage(self) -> float:
        with self._lock:
            v = self._operating_point()[0]
            return v + (self._rng.gauss(0.0, self._noise_v) if self._noise_v else 0.0)

    def measure_current(self) -> float:
        with self._lock:
            i = self._operating_point()[1]
            return i + (self._rng.gauss(0.0, self._noise_a) if self._noise_a else 0.0)

    # commands ----------------------------------------------------------------------------------
    def set_output(self, on: bool) -> None:
        with self._lock:
            if on and not self._output:
                if self._t is None:
                    raise RuntimeError("PsuModel: call advance_to(bench time) before switching the output on")
                self._on_since = self._t
            if not on:
                self._on_since = None
            self._output = bool(on)

    def set_voltage(self, volts: float) -> None:
        with self._lock:
            if not 0.0 <= volts <= self.max_voltage_v:
                raise ScpiError(-222)
            self._voltage = float(volts)

    def set_current_limit(self, amps: float) -> None:
        with self._lock:
            if not 0.0 <= amps <= self.max_current_a:
                raise ScpiError(-222)
            self._current_limit = float(amps)

    def set_load(self, *, resistance_ohm: float | None = None, current_a: float | None = None) -> None:
        """Change the load: ``resistance_ohm`` (``math.inf`` = open) and/or a constant-current sink."""
        with self._lock:
            if resistance_ohm is not None:
                if not resistance_ohm > 0:
                    raise ValueError(f"PsuModel: load resistance must be > 0 ohm, got {resistance_ohm}")
                self._load_ohm = float(resistance_ohm)
            if current_a is not None:
                if current_a < 0:
                    raise ValueError(f"PsuModel: load current must be >= 0 A, got {current_a}")
                self._load_current = float(current_a)

    def reset(self) -> None:
        """``*RST``: output off, 0 V, 1 A limit."""
        with self._lock:
            self._output, self._on_since = False, None
            self._voltage, self._current_limit = 0.0, min(1.0, self.max_current_a)

    # electrical ----------------------------------------------------------------------------------
    def _load_at(self, volts: float) -> float:
        if volts <= 0:
            return 0.0
        return volts / self._load_ohm + self._load_current

    def _operating_point(self) -> tuple[float, float]:
        if not self._output:
            return 0.0, 0.0
        v = self._voltage
        if self._load_at(v) <= self._current_limit:
            return v, self._load_at(v)
        # CC: the limit current flows; the sink takes its share first, the resistor sets the voltage
        left = self._current_limit - self._load_current
        if left <= 0 or math.isinf(self._load_ohm):
            return 0.0, self._current_limit if self._load_current > 0 else 0.0
        return min(v, left * self._load_ohm), self._current_limit


# ---------------------------------------------------------------------------------------------
# SCPI front end
# ---------------------------------------------------------------------------------------------
def _split_keyword(spec: str) -> tuple[str, str, bool]:
    optional = spec.startswith("[") and spec.endswith("]")
    word = spec.strip("[]")
    short = "".join(ch for ch in word if ch.isupper())
    return short, word.upper(), optional


class ScpiCommand:
    """A header pattern like ``[SOURce]:VOLTage:[LEVel]`` plus set/query handlers."""

    def __init__(self, pattern: str, setter: Callable[[list[str]], None] | None = None,
                 getter: Callable[[list[str]], str] | None = None) -> None:
        self.keywords = [_split_keyword(spec) for spec in pattern.split(":")]
        self.setter = setter
        self.getter = getter

    def matches(self, tokens: list[str]) -> bool:
        return self._match(tokens, 0, 0)

    def _match(self, tokens: list[str], i: int, j: int) -> bool:
        if j == len(self.keywords):
            return i == len(tokens)
        short, long, optional = self.keywords[j]
        if i < len(tokens) and tokens[i].upper() in (short, long) and self._match(tokens, i + 1, j + 1):
            return True
        return optional and self._match(tokens, i, j + 1)


_NUMBER_WITH_UNIT = re.compile(r"([+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?)\s*(m?[VA])?", re.IGNORECASE)


def _query(read: Callable[[], str]) -> Callable[[list[str]], str]:
    """A query handler taking no parameters (-108 if some are given)."""
    def run(args: list[str]) -> str:
        if args:
            raise ScpiError(-108)
        return read()
    return run


def nr3(value: float) -> str:
    return f"{value:.6E}"


class PsuSimulator(LineServer):
    """SCPI power supply on TCP.  Requests end with ``\\n`` (``\\r\\n`` accepted); replies ``\\n``."""

    name = "scpi-psu"

    def __init__(self, model: PsuModel, clock: Clock, *, idn: str = DEFAULT_IDN, host: str = "127.0.0.1",
                 port: int = 0) -> None:
        super().__init__(host, port, request_terminator=b"\n", reply_terminator=b"\n")
        self.model = model
        self.clock = clock
        self.idn = idn
        self._errors: deque[int] = deque()
        self._errors_lock = threading.Lock()
        model_ = self.model
        self.commands = [
            ScpiCommand("OUTPut:[STATe]", self._set_output,
                        _query(lambda: "1" if model_.output_on else "0")),
            ScpiCommand("[SOURce]:VOLTage:[LEVel]:[IMMediate]:[AMPLitude]",
                        lambda a: model_.set_voltage(self._number(a, "V")),
                        _query(lambda: nr3(model_.voltage_setting))),
            ScpiCommand("[SOURce]:CURRent:[LEVel]:[IMMediate]:[AMPLitude]",
                        lambda a: model_.set_current_limit(self._number(a, "A")),
                        _query(lambda: nr3(model_.current_limit))),
            ScpiCommand("MEASure:[SCALar]:VOLTage:[DC]", None, _query(lambda: nr3(model_.measure_voltage()))),
            ScpiCommand("MEASure:[SCALar]:CURRent:[DC]", None, _query(lambda: nr3(model_.measure_current()))),
            ScpiCommand("SYSTem:ERRor:[NEXT]", None, _query(self._pop_error)),
        ]

    # error queue (instrument-global) --------------------------------------------------------------
    def push_error(self, code: int) -> None:
        with self._errors_lock:
            if len(self._errors) >= 20:
                self._errors[-1] = -350
            else:
                self._errors.append(code)

    def _pop_error(self) -> str:
        with self._errors_lock:
            code = self._errors.popleft() if self._errors else 0
        return f'{code},"{SCPI_ERRORS[code]}"'

    def error_queue(self) -> list[int]:
        with self._errors_lock:
            return list(self._errors)

    # line handling ---------------------------------------------------------------------------
    def handle_line(self, session: Any, line: bytes) -> bytes | None:
        self.model.advance_to(self.clock.now())
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            self.push_error(-102)
            return None
        outputs: list[str] = []
        prefix: list[str] = []
        for unit in text.split(";"):
            unit = unit.strip()
            if not unit:
                continue
            try:
                result, prefix = self._unit(unit, prefix)
            except ScpiError as exc:
                self.push_error(exc.code)
                continue
            if result is not None:
                outputs.append(result)
        if not outputs:
            return None
        return (";".join(outputs) + "\n").encode("ascii")

    def _unit(self, unit: str, prefix: list[str]) -> tuple[str | None, list[str]]:
        parts = unit.split(None, 1)
        header = parts[0]
        args = [] if len(parts) == 1 else [a.strip() for a in parts[1].split(",")]
        if header.startswith("*"):
            return self._common(header, args), prefix
        is_query = header.endswith("?")
        body = header[:-1] if is_query else header
        absolute = body.startswith(":")
        tokens = (body[1:] if absolute else body).split(":")
        if not all(re.fullmatch(r"[A-Za-z]+", t) for t in tokens):
            raise ScpiError(-102)
        full = tokens if absolute else prefix + tokens
        command = next((c for c in self.commands if c.matches(full)), None)
        if command is None:
            raise ScpiError(-113)
        new_prefix = full[:-1]
        if is_query:
            if command.getter is None:
                raise ScpiError(-113)
            return command.getter(args), new_prefix
        if command.setter is None:
            raise ScpiError(-113)
        command.setter(args)
        return None, new_prefix

    def _common(self, header: str, args: list[str]) -> str | None:
        upper = header.upper()
        if args:
            raise ScpiError(-108)
        if upper == "*IDN?":
            return self.idn
        if upper == "*OPC?":
            return "1"
        if upper == "*CLS":
            with self._errors_lock:
                self._errors.clear()
            return None
        if upper == "*RST":
            self.model.reset()
            return None
        if upper == "*OPC":
            return None
        raise ScpiError(-113)

    # argument helpers --------------------------------------------------------------------------
    @staticmethod
    def _number(args: list[str], unit: str) -> float:
        if not args or args == [""]:
            raise ScpiError(-109)
        if len(args) > 1:
            raise ScpiError(-108)
        match = _NUMBER_WITH_UNIT.fullmatch(args[0])
        if not match:
            raise ScpiError(-104)
        value = float(match.group(1))
        suffix = (match.group(2) or "").upper()
        if suffix and suffix[-1] != unit:
            raise ScpiError(-104)
        return value / 1000.0 if suffix.startswith("M") else value

    def _set_output(self, args: list[str]) -> None:
        if not args or args == [""]:
            raise ScpiError(-109)
        if len(args) > 1:
            raise ScpiError(-108)
        word = args[0].upper()
        if word in ("ON", "1"):
            self.model.set_output(True)
        elif word in ("OFF", "0"):
            self.model.set_output(False)
        else:
            raise ScpiError(-104)


class _SelectedChannel:
    """The channel model the last ``INST:NSEL`` chose (what the one-channel commands act on)."""

    def __init__(self, sim: "MultiChannelPsuSimulator") -> None:
        self._sim = sim

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sim.models[self._sim.selected - 1], name)


class MultiChannelPsuSimulator(PsuSimulator):
    """A supply with several outputs (``models``, channel 1..N): ``INSTrument[:SELect]:NSELect n``
    selects the channel the other commands act on (``INST:NSEL?`` reads it back); out of range ->
    ``-222,"Data out of range"``.  ``*RST`` resets every channel and selects channel 1."""

    name = "scpi-psu-multi"

    def __init__(self, models: list[PsuModel], clock: Clock, **kwargs: Any) -> None:
        if not models:
            raise ValueError("a multi-channel supply needs at least one channel model")
        self.models = list(models)
        self.selected = 1
        super().__init__(_SelectedChannel(self), clock, **kwargs)   # type: ignore[arg-type]
        self.commands.append(ScpiCommand("INSTrument:[SELect]:NSELect", self._select,
                                         _query(lambda: str(self.selected))))

    def handle_line(self, session: Any, line: bytes) -> bytes | None:
        now = self.clock.now()
        for model in self.models:          # a line may select any channel: every one at this bench instant
            model.advance_to(now)
        return super().handle_line(session, line)

    def _select(self, args: list[str]) -> None:
        value = self._number(args, "")
        if value != int(value) or not 1 <= int(value) <= len(self.models):
            raise ScpiError(-222)
        self.selected = int(value)

    def _common(self, header: str, args: list[str]) -> str | None:
        if header.upper() == "*RST" and not args:
            for model in self.models:
                model.reset()
            self.selected = 1
            return None
        return super()._common(header, args)

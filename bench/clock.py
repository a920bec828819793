"""One clock for the whole bench: simulators, drivers' timeouts that are bench-time, and the engine.

Time is "bench seconds" on a Unix-like axis (float seconds).  Three implementations:

- ``RealClock``: wall time.  Production with real hardware.
- ``AcceleratedClock(speed)``: bench time runs ``speed`` times faster than the wall.  It is fully
  described by ``(speed, wall_epoch, bench_epoch)`` so two processes (a free-running simulator and
  its driver) that share those three numbers agree on the time without talking.
- ``SteppedClock``: time only moves when someone calls ``advance`` or ``sleep``; deterministic tests.
- ``LockstepClock(pace)``: the simulated bench's clock.  Bench time moves only when the run's
  scheduler sleeps, and each new instant is first *served* by every simulator registered with
  ``serve(name, fn)`` (w1 files rewritten, gyro frames up to that instant written on the line) and
  then *received* by every driver registered with ``receive(name, fn)`` (the gyro link has read those
  bytes) before ``sleep`` returns.  ``pace`` is a limit: never faster than ``pace`` x wall; ``None``
  runs as fast as the host can.  A busy host only slows the run; the data do not change.  Across
  processes (``bench sim up``) the simulators' lockstep clock is driven from the engine's process over
  a clock endpoint (``bench.clocklink``; ``clock_from_json`` of kind ``lockstep_link``).

Network I/O (socket timeouts) is always in wall seconds; only waiting *for the bench* (soaks, record
durations, settle times) uses the clock.
"""
from __future__ import annotations

import collections
import threading
import time
from pathlib import Path
from dataclasses import dataclass
from typing import Any, Callable, Protocol


class Clock(Protocol):
    speed: float

    def now(self) -> float:
        """Current bench time in seconds."""

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of bench time."""

    def to_json(self) -> dict[str, Any]:
        """Parameters another process needs to rebuild the same clock."""


class RealClock:
    speed = 1.0

    def now(self) -> float:
        return time.time()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def to_json(self) -> dict[str, Any]:
        return {"kind": "real"}


@dataclass
class AcceleratedClock:
    """Bench time = bench_epoch + (wall - wall_epoch) * speed."""

    speed: float = 3600.0
    wall_epoch: float | None = None
    bench_epoch: float | None = None

    def __post_init__(self) -> None:
        if self.speed <= 0:
            raise ValueError(f"clock speed must be > 0, got {self.speed}")
        now = time.time()
        if self.wall_epoch is None:
            self.wall_epoch = now
        if self.bench_epoch is None:
            self.bench_epoch = self.wall_epoch

    def now(self) -> float:
        return self.bench_epoch + (time.time() - self.wall_epoch) * self.speed

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.speed)

    def wall_seconds(self, bench_seconds: float) -> float:
        return bench_seconds / self.speed

    def to_json(self) -> dict[str, Any]:
        return {"kind": "accelerated", "speed": self.speed, "wall_epoch": self.wall_epoch,
                "bench_epoch": self.bench_epoch}


class SteppedClock:
    """Deterministic clock: ``sleep`` advances time instantly; other threads see the new time.

    ``speed`` is reported as infinite so code that converts bench time to wall timeouts uses zero.
    """

    speed = float("inf")

    def __init__(self, start: float = 1_700_000_000.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def advance(self, seconds: float) -> float:
        if seconds < 0:
            raise ValueError("a stepped clock cannot go backwards")
        with self._lock:
            self._t += seconds
            return self._t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)
        time.sleep(0)  # let other threads run

    def to_json(self) -> dict[str, Any]:
        return {"kind": "stepped", "now": self.now()}


ServeFn = Callable[[float], dict[str, Any] | None]
ReceiveFn = Callable[[float, dict[str, dict[str, Any]]], None]


class LockstepClock:
    """Bench time that advances only in ``sleep``/``advance_to`` and only after every sample due at
    the new instant has been served and received (see the module docstring).

    One thread drives the time (the run engine); other threads only read ``now()``.  Tests can hold
    the time: ``hold_at(t)`` makes the driving thread stop at bench time ``t`` (after serving it) until
    ``release()``; ``wait_held(timeout)`` waits until it got there.  Across processes the same is done
    with ``hold_file``: while that file holds a bench time the clock stops there, and writes that time
    to ``<hold_file>.held`` once it got there; emptying or removing the file releases it.
    """

    lockstep = True
    BURST_WALL_S = 0.25        # how far the pace may catch up after a slow stretch

    def __init__(self, start: float | None = None, pace: float | None = 3600.0, *,
                 hold_file: str | None = None) -> None:
        if pace is not None and pace <= 0:
            raise ValueError(f"clock pace must be > 0 (or None for as fast as possible), got {pace}")
        self._t = float(time.time() if start is None else start)
        self.pace = pace
        self.speed = float(pace) if pace is not None else float("inf")
        self._servers: dict[str, ServeFn] = {}
        self._receivers: dict[str, ReceiveFn] = {}
        self._lock = threading.RLock()
        self._cond = threading.Condition()
        self._hold: float | None = None
        self._held = False
        self.hold_file = hold_file
        self._wall_mark = time.monotonic()
        self.fixed_outage_s: float | None = None
        self._recent: collections.deque[tuple[float, float]] = collections.deque(maxlen=500)
        self.instants = 0
        self.wall_cost_s: dict[str, float] = {}     # wall seconds spent serving / receiving, by name
        self.last_reports: dict[str, dict[str, Any]] = {}

    # ---- reading -------------------------------------------------------------------------------
    def now(self) -> float:
        return self._t

    def to_json(self) -> dict[str, Any]:
        doc = {"kind": "lockstep", "now": self._t, "pace": self.pace}
        if self.hold_file:
            doc["hold_file"] = self.hold_file
        return doc

    # ---- participants --------------------------------------------------------------------------
    def serve(self, name: str, fn: ServeFn) -> None:
        """``fn(t)`` makes everything due at bench time ``t`` available on its transport; it may
        return a small report (e.g. bytes written) handed to the receivers."""
        with self._lock:
            self._servers[name] = fn

    def receive(self, name: str, fn: ReceiveFn) -> None:
        """``fn(t, reports)`` returns once the driver has taken in what the servers reported."""
        with self._lock:
            self._receivers[name] = fn

    def participants(self) -> list[str]:
        """Names of the participants that serve each instant, in serving order."""
        with self._lock:
            return list(self._servers)

    def forget(self, name: str) -> None:
        with self._lock:
            self._servers.pop(name, None)
            self._receivers.pop(name, None)

    # ---- driving -------------------------------------------------------------------------------
    def sleep(self, seconds: float) -> None:
        self.advance_to(self._t + max(0.0, seconds))

    def advance_to(self, t: float) -> float:
        with self._lock:
            while t > self._t:
                self._read_hold_file()
                hold = self._hold
                if hold is not None and self._t >= hold:
                    self._wait_release(hold)           # stands at the hold until it is moved or lifted
                    continue
                step_to = t if hold is None else min(t, hold)
                self._pace(step_to - self._t)
                self._t = step_to
                self._serve(step_to)
            if t == self._t and self.instants == 0:
                self._serve(t)
            return self._t

    def jump_to(self, t: float) -> None:
        """Set the bench time without pacing, then serve it: restoring a checkpointed bench (which may
        go back to the checkpoint's instant) and letting an outage pass in one step.  Not for runs."""
        with self._lock:
            self._t = float(t)
            self._wall_mark = time.monotonic()
            self._serve(self._t)

    def outage_bench_s(self, wall_s: float) -> float:
        """Bench seconds an outage of ``wall_s`` wall seconds lasts: ``fixed_outage_s`` when set (``bench
        resume --outage``), else at the pace limit (x3600 when unpaced, the default pace)."""
        if self.fixed_outage_s is not None:
            return self.fixed_outage_s
        return max(0.0, wall_s) * (self.pace or 3600.0)

    def serve_now(self) -> None:
        """Serve the current instant again (a participant registered after the clock last moved)."""
        with self._lock:
            self._serve(self._t)

    def _pace(self, bench_s: float) -> None:
        if self.pace is None:
            return
        # the next instant is due one step after this one; only the time the host fell behind that
        # instant by more than BURST_WALL_S is forgotten (the work done at an instant is not lateness)
        wall = time.monotonic()
        self._wall_mark = max(self._wall_mark + bench_s / self.pace, wall - self.BURST_WALL_S)
        if self._wall_mark > wall:
            time.sleep(self._wall_mark - wall)

    def _serve(self, t: float) -> None:
        reports: dict[str, dict[str, Any]] = {}
        cost = self.wall_cost_s
        for name, fn in list(self._servers.items()):
            w0 = time.perf_counter()
            reports[name] = fn(t) or {}
            cost[name] = cost.get(name, 0.0) + time.perf_counter() - w0
        for name, fn in list(self._receivers.items()):
            w0 = time.perf_counter()
            fn(t, reports)
            cost[name] = cost.get(name, 0.0) + time.perf_counter() - w0
        self.last_reports = reports
        self.instants += 1
        self._recent.append((time.monotonic(), t))

    def effective_speed(self) -> float | None:
        """Bench seconds per wall second over the last few hundred instants (None before two)."""
        recent = list(self._recent)
        if len(recent) < 2 or recent[-1][0] <= recent[0][0]:
            return None
        return (recent[-1][1] - recent[0][1]) / (recent[-1][0] - recent[0][0])

    # ---- holding (tests) -----------------------------------------------------------------------
    def hold_at(self, t: float) -> None:
        """Stop the driving thread at bench time ``t``; moves a hold it stands at (it goes on to ``t``).
        Holding again at the same instant changes nothing."""
        with self._cond:
            if self._hold == float(t):
                return
            self._hold = float(t)
            self._held = False
            self._cond.notify_all()

    def release(self) -> None:
        with self._cond:
            self._hold = None
            self._held = False
            self._cond.notify_all()

    def wait_held(self, timeout_s: float = 60.0) -> bool:
        """True once the driving thread stopped at the hold instant (within ``timeout_s`` wall s)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._held, timeout_s)

    @property
    def held(self) -> bool:
        return self._held

    def _read_hold_file(self) -> None:
        if self.hold_file is None:
            return
        try:
            text = Path(self.hold_file).read_text().strip()
        except FileNotFoundError:
            text = ""
        self._hold = float(text) if text else None

    def _wait_release(self, hold: float) -> None:
        if self.hold_file is not None:
            marker = Path(self.hold_file + ".held")
            tmp = Path(self.hold_file + ".held.tmp")
            tmp.write_text(repr(hold))
            tmp.replace(marker)
            while self._hold == hold:
                time.sleep(0.02)
                self._read_hold_file()
            return
        with self._cond:
            if self._hold != hold:
                return
            self._held = True
            self._cond.notify_all()
            self._cond.wait_for(lambda: self._hold != hold)


def clock_from_json(data: dict[str, Any]) -> Clock:
    kind = data.get("kind")
    if kind == "real":
        return RealClock()
    if kind == "accelerated":
        return AcceleratedClock(float(data["speed"]), float(data["wall_epoch"]), float(data["bench_epoch"]))
    if kind == "stepped":
        return SteppedClock(float(data["now"]))
    if kind == "lockstep":
        return LockstepClock(float(data["now"]), data.get("pace"), hold_file=data.get("hold_file"))
    if kind == "lockstep_link":      # a simulated bench in another process, driven from this one
        from bench.clocklink import clock_from_link_json

        return clock_from_link_json(data)
    raise ValueError(f"unknown clock kind {kind!r} in clock description {data!r}")


def parse_speed(text: str | float | None, what: str = "--speed") -> float | None:
    """``--speed`` of the simulated bench: a number > 0 (bench seconds per wall second at most) or
    ``max`` (as fast as the host can: returns None)."""
    if text is None:
        return 3600.0
    if isinstance(text, str) and text.strip().lower() == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{what} must be a number > 0 or 'max', got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise ValueError(f"{what} must be a number > 0 or 'max', got {text!r}")
    return value


def make_clock(speed: float | None) -> Clock:
    """``None`` or 1 -> real time; anything else -> accelerated by that factor."""
    if speed is None or speed == 1:
        return RealClock()
    return AcceleratedClock(float(speed))


class Deadline:
    """A deadline in bench seconds that stays meaningful on an accelerated clock.

    At x3600 one poll round trip to a device (a few wall milliseconds) costs several bench seconds, so
    a bench-time timeout alone could expire before the first reply.  On an accelerated clock the
    deadline therefore also waits ``min_wall_s`` of wall time; on a real or stepped clock it is exact.
    """

    def __init__(self, clock: Clock, bench_s: float, min_wall_s: float = 2.0) -> None:
        self.clock = clock
        self.bench_deadline = clock.now() + bench_s
        speed = getattr(clock, "speed", 1.0)
        accelerated = speed > 1 and speed != float("inf") and not getattr(clock, "lockstep", False)
        self.wall_deadline = time.monotonic() + (min_wall_s if accelerated else 0.0)

    def passed(self) -> bool:
        return self.clock.now() >= self.bench_deadline and time.monotonic() >= self.wall_deadline

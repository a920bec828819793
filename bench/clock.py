"""One clock for the whole bench: simulators, drivers' timeouts that are bench-time, and the engine.

Time is "bench seconds" on a Unix-like axis (float seconds).  Three implementations:

- ``RealClock``: wall time.  Production with real hardware.
- ``AcceleratedClock(speed)``: bench time runs ``speed`` times faster than the wall.  It is fully
  described by ``(speed, wall_epoch, bench_epoch)`` so two processes (``bench sim up`` and
  ``bench run``) that share those three numbers agree on the time without talking.
- ``SteppedClock``: time only moves when someone calls ``advance`` or ``sleep``; deterministic tests.

Network I/O (socket timeouts) is always in wall seconds; only waiting *for the bench* (soaks, record
durations, settle times) uses the clock.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol


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


def clock_from_json(data: dict[str, Any]) -> Clock:
    kind = data.get("kind")
    if kind == "real":
        return RealClock()
    if kind == "accelerated":
        return AcceleratedClock(float(data["speed"]), float(data["wall_epoch"]), float(data["bench_epoch"]))
    if kind == "stepped":
        return SteppedClock(float(data["now"]))
    raise ValueError(f"unknown clock kind {kind!r} in clock description {data!r}")


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
        accelerated = speed > 1 and speed != float("inf")
        self.wall_deadline = time.monotonic() + (min_wall_s if accelerated else 0.0)

    def passed(self) -> bool:
        return self.clock.now() >= self.bench_deadline and time.monotonic() >= self.wall_deadline

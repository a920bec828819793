"""Conditions that suspend a run, as small objects (Bluesky's ``suspenders.py`` is the model), and
the state of an open suspension.

A ``Suspender`` watches one thing the acquisition reads (``Watched``: ``bench.engine.monitor.
Acquisition``) and says, after each read of its ``source`` ("gyro", "probes", "chamber", "table",
"psu"), whether its condition holds: a reason text, or None.  Every condition in force suspends the
run (``bench.engine.engine``); the run resumes once all are clear for ``EngineConfig.settle_s``.

``device_suspenders`` are the bench's own (a link down, gyro frames stopped, probes unreadable or
lost, a chamber alarm or input error); a bench config adds thresholds on a reading with
``BenchConfig.suspend`` (``SuspendRule`` -> ``SuspendFloor`` / ``SuspendCeil``), for example the
supply current above a ceiling or a probe below a floor.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Protocol

from bench.config import BenchConfig, SuspendRule
from bench.engine.config import EngineConfig
from bench.engine.store import PsuReading
from bench.interfaces import ChamberStatus

SOURCES = ("gyro", "probes", "chamber", "table", "psu")
LINK_LABELS = {"gyro": "gyro", "chamber": "chamber", "table": "turntable", "psu": "power supply"}


class Watched(Protocol):
    """What suspenders read (kept up to date by the acquisition)."""

    cfg: EngineConfig
    link_errors: dict[str, str]            # source -> error of its last read, absent once a read succeeds
    powered_since: float | None            # gyro power on since (None: off)
    last_frames_t: float | None
    probe_read_failures: int               # consecutive failed reads of the probe bus
    probe_bad: dict[str, int]              # probe -> consecutive missing / rejected readings
    probe_fault: dict[str, str]            # probe -> why its last reading was missing / rejected
    status: ChamberStatus | None           # last chamber status read
    psu: PsuReading | None                 # last power supply reading

    def latest_probes(self) -> dict[str, float | None]: ...


class Suspender:
    """One suspend condition: ``check`` returns the reason while it holds, else None."""

    source: str
    key: str

    def check(self, data: Watched, now: float) -> str | None:
        raise NotImplementedError


@dataclass
class LinkDown(Suspender):
    source: str

    def __post_init__(self) -> None:
        self.key = f"{self.source}_link"

    def check(self, data: Watched, now: float) -> str | None:
        error = data.link_errors.get(self.source)
        return None if error is None else f"{LINK_LABELS[self.source]} link down: {error}"


class GyroFramesStopped(Suspender):
    source, key = "gyro", "gyro_frames"

    def check(self, data: Watched, now: float) -> str | None:
        powered_since = data.powered_since
        if powered_since is None or now - powered_since < data.cfg.frames_grace_s:
            return None
        last = max(powered_since, data.last_frames_t) if data.last_frames_t is not None else powered_since
        silent = now - last
        return (f"gyro frames stopped: none for {silent:.0f} s with power on"
                if silent > data.cfg.frames_timeout_s else None)


class ProbesUnreadable(Suspender):
    source, key = "probes", "probes_link"

    def check(self, data: Watched, now: float) -> str | None:
        failures = data.probe_read_failures
        if failures < data.cfg.probe_lost_reads:
            return None
        return f"probes unreadable ({failures} reads): {data.link_errors.get('probes')}"


@dataclass
class ProbeLost(Suspender):
    name: str
    source = "probes"

    def __post_init__(self) -> None:
        self.key = f"probe:{self.name}"

    def check(self, data: Watched, now: float) -> str | None:
        if data.probe_bad.get(self.name, 0) < data.cfg.probe_lost_reads:
            return None
        return f"probe {self.name} lost: {data.probe_fault.get(self.name)}"


class ChamberAlarm(Suspender):
    source, key = "chamber", "chamber_alarm"

    def check(self, data: Watched, now: float) -> str | None:
        status = data.status
        return f"chamber alarm {status.alarm}" if status is not None and status.alarm else None


class ChamberInputError(Suspender):
    source, key = "chamber", "chamber_input"

    def check(self, data: Watched, now: float) -> str | None:
        status = data.status
        return f"chamber input error {status.input_error}" if status is not None and status.input_error else None


# ---- thresholds on a reading (Bluesky's SuspendFloor / SuspendCeil) ----------------------------
def signal_source(signal: str) -> str:
    if signal.startswith("probe:"):
        return "probes"
    return {"chamber_pv_c": "chamber", "psu_volts": "psu", "psu_amps": "psu"}[signal]


def signal_value(data: Watched, signal: str) -> float | None:
    """The latest value of ``signal`` (None until it has been read)."""
    if signal.startswith("probe:"):
        return data.latest_probes().get(signal.removeprefix("probe:"))
    if signal == "chamber_pv_c":
        return data.status.pv_c if data.status is not None else None
    if data.psu is None:
        return None
    return data.psu.volts if signal == "psu_volts" else data.psu.amps


@dataclass
class _Threshold(Suspender):
    """Trips when ``signal`` passes ``threshold``; clears once it is back at ``resume_at`` (default the
    threshold).  A value not read yet leaves the verdict as it was."""

    signal: str
    threshold: float
    resume_at: float | None = None
    reason: str | None = field(default=None, init=False)   # set while tripped

    def __post_init__(self) -> None:
        self.source = signal_source(self.signal)
        self.key = f"{self.word}:{self.signal}"
        if self.resume_at is None:
            self.resume_at = self.threshold

    word = ""

    def tripped_by(self, value: float) -> bool:
        raise NotImplementedError

    def cleared_by(self, value: float) -> bool:
        raise NotImplementedError

    def check(self, data: Watched, now: float) -> str | None:
        value = signal_value(data, self.signal)
        if value is not None:
            if self.reason is None and self.tripped_by(value):
                self.reason = f"{self.signal} {value:.4g} {self.word} {self.threshold:g}"
            elif self.reason is not None and self.cleared_by(value):
                self.reason = None
        return self.reason


class SuspendFloor(_Threshold):
    """Suspend while ``signal`` < ``threshold``; resume at ``signal`` >= ``resume_at``."""

    word = "below"

    def tripped_by(self, value: float) -> bool:
        return value < self.threshold

    def cleared_by(self, value: float) -> bool:
        assert self.resume_at is not None
        return value >= self.resume_at


class SuspendCeil(_Threshold):
    """Suspend while ``signal`` > ``threshold``; resume at ``signal`` <= ``resume_at``."""

    word = "above"

    def tripped_by(self, value: float) -> bool:
        return value > self.threshold

    def cleared_by(self, value: float) -> bool:
        assert self.resume_at is not None
        return value <= self.resume_at


def from_rule(rule: SuspendRule) -> Suspender:
    if rule.below is not None:
        return SuspendFloor(rule.signal, rule.below, rule.resume_at)
    assert rule.above is not None
    return SuspendCeil(rule.signal, rule.above, rule.resume_at)


def device_suspenders(probe_names: Iterable[str]) -> list[Suspender]:
    """The bench's own conditions, in the order their reasons are listed."""
    return [LinkDown("gyro"), GyroFramesStopped(), ProbesUnreadable(),
            *(ProbeLost(name) for name in probe_names),
            LinkDown("chamber"), ChamberAlarm(), ChamberInputError(), LinkDown("table"), LinkDown("psu")]


def bench_suspenders(config: BenchConfig, probe_names: Iterable[str]) -> list[Suspender]:
    return [*device_suspenders(probe_names), *(from_rule(rule) for rule in config.suspend)]


# ---- the state of an open suspension ------------------------------------------------------------
@dataclass
class Suspension:
    """An open suspension: its store id, since when, the reason (every kind of condition seen while
    it is open) and, while settling, since when every condition has been clear."""

    id: Any
    t_from: float
    reason: str
    keys: set[str]
    clear_since: float | None = None

    @classmethod
    def opened(cls, sid: Any, now: float, conditions: dict[str, str]) -> "Suspension":
        return cls(sid, now, "; ".join(conditions.values()), set(conditions))

    def add(self, conditions: dict[str, str]) -> list[str]:
        """Take in the conditions now in force; returns the texts of new kinds of condition (a
        condition whose text changes is the same one)."""
        new = [text for key, text in conditions.items() if key not in self.keys]
        for key in conditions:
            self.keys.add(key)
        for text in new:
            self.reason += "; " + text
        return new

    def checkpoint(self) -> dict[str, Any]:
        return {"id": self.id, "t_from": self.t_from, "reason": self.reason}

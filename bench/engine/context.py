"""What a step executor may see and do: the narrow ``StepContext`` the engine hands to each step.

Executors (``bench.engine.executors``) never see the engine: they command the devices, read the
acquisition's latest data (``StepReadings``), keep the commanded ``HardwareState`` up to date (the
engine checkpoints it and restores it on resume), log events, and report through hooks: a finished
recording piece (``record_segment``), a fit result (``save_fit``), the gyro power switching
(``gyro_powered``).  ``fit`` runs the bench's fit hook, or is None when none is wired.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Protocol

from bench.config import BenchConfig
from bench.engine.config import EngineConfig
from bench.engine.devices import Devices
from bench.engine.steps import Fit
from bench.interfaces import ChamberStatus

LogFn = Callable[..., None]


@dataclass
class HardwareState:
    """What the engine last commanded (restored on resume)."""

    chamber_setpoint_c: float | None = None
    chamber_ramp: dict[str, float] | None = None
    orientation: str | None = None
    table_angles: list[float] | None = None
    table_rates: dict[str, float] = field(default_factory=dict)
    gyro_power: bool | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "HardwareState":
        return cls(**data)


class StepReadings(Protocol):
    """The acquisition's data a step decides on (``bench.engine.monitor.Acquisition``)."""

    status: ChamberStatus | None          # last chamber status read
    status_t: float | None                # ... and when
    probe_reads: int                      # successful probe reads so far
    probe_names: list[str]

    def read_chamber(self, now: float) -> ChamberStatus | None: ...
    def latest_probes(self) -> dict[str, float | None]: ...
    def probe_rate_c_per_min(self, name: str, now: float, window_s: float) -> float | None: ...


@dataclass(frozen=True)
class StepContext:
    devices: Devices
    config: BenchConfig
    engine_config: EngineConfig
    hw: HardwareState
    readings: StepReadings
    log: LogFn
    record_segment: Callable[[int, str, float, float, dict[str, Any]], None]   # index, kind, t_from, t_to, labels
    save_fit: Callable[[int, dict[str, Any]], None]                            # index, result
    gyro_powered: Callable[[float, bool], None]                                # now, on
    fit: Callable[[int, Fit], dict[str, Any]] | None = None                    # index, step -> result

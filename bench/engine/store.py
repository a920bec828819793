"""What the engine persists, as a small Protocol (``RunStore``).

The engine depends only on this; ``bench.storage`` gets an adapter (``SqlRunStore``) and unit tests
use ``bench.engine.memstore.MemoryRunStore``.  All times are bench seconds.  Every value passed is
plain JSON-able data except frames (``GyroFrame``) and probe readings (``ProbeReading``).

Contract notes
- ``add_frames`` appends in order; the *store* assigns frame indexes (0, 1, 2, ... per run), so
  frames are never numbered twice, also across a crash and ``resume``.
- ``save_checkpoint`` replaces the previous checkpoint of the run atomically; ``load_checkpoint``
  returns the last one (or None).  The checkpoint holds the plan position, the step's own state
  (elapsed time...), the commanded hardware state and progress (see ``Engine`` for the layout).
- ``open_suspension`` returns an id that ``close_suspension`` takes back.
- ``add_telemetry``: any of chamber / turntable ({axis number: AxisState}) / psu may be None when
  that device could not be read at that time.
- ``add_segment``: ``kind`` is the step kind that produced it (record, soak, ramp, wait_stable);
  ``labels`` holds the procedure's labels (temperature_c, position, repetition, set, phase...) plus
  ``piece`` (0, 1... when a pause, suspension or crash split the step) and ``complete``.
- Run status values: running, paused, suspended, stopping, completed, stopped, aborted, failed
  ("stopped" = ended early on an operator stop, after finishing the current recording).
- Step status values: running, done, skipped, stopped, aborted, failed.
- ``unit_runs``: for a multi-gyro run, slot -> the run id of that gyro's own run (the child run that
  takes its frames, probes, supply telemetry, segments and gaps); empty for a one-gyro run.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, Sequence

from bench.interfaces import AxisState, ChamberStatus, GyroFrame, ProbeReading


@dataclass(frozen=True)
class PsuReading:
    volts: float
    amps: float
    on: bool


class RunStore(Protocol):
    def create_run(self, run_id: str, plan: dict[str, Any], summary: dict[str, Any], t: float) -> None: ...

    def load_plan(self, run_id: str) -> dict[str, Any]: ...

    def set_run_status(self, run_id: str, status: str, t: float, reason: str | None = None) -> None: ...

    def save_checkpoint(self, run_id: str, checkpoint: dict[str, Any]) -> None: ...

    def load_checkpoint(self, run_id: str) -> dict[str, Any] | None: ...

    def set_step_status(self, run_id: str, index: int, kind: str, status: str, t: float,
                        info: dict[str, Any] | None = None) -> None: ...

    def add_event(self, run_id: str, t: float, level: str, kind: str, message: str,
                  data: dict[str, Any] | None = None) -> None: ...

    def add_frames(self, run_id: str, frames: Sequence[GyroFrame]) -> None: ...

    def last_frame_time(self, run_id: str) -> float | None: ...

    def add_probe_readings(self, run_id: str, t: float, readings: Sequence[ProbeReading]) -> None: ...

    def add_telemetry(self, run_id: str, t: float, chamber: ChamberStatus | None,
                      turntable: dict[int, AxisState] | None, psu: PsuReading | None) -> None: ...

    def add_segment(self, run_id: str, step_index: int, kind: str, t_from: float, t_to: float,
                    labels: dict[str, Any]) -> None: ...

    def add_gap(self, run_id: str, t_from: float, t_to: float, reason: str,
                frames_missing: int | None = None) -> None: ...

    def open_suspension(self, run_id: str, t_from: float, reason: str) -> Any: ...

    def close_suspension(self, run_id: str, suspension_id: Any, t_to: float, reason: str) -> None: ...

    def save_fit(self, run_id: str, step_index: int, result: dict[str, Any]) -> None: ...

    def unit_runs(self, run_id: str) -> dict[str, str]: ...

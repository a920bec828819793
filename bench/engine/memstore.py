"""In-memory ``RunStore`` (unit tests, dry runs).  Keeps everything in lists; copies JSON-able
inputs so later mutation by the caller cannot change what was stored."""
from __future__ import annotations

import copy
import threading
from dataclasses import dataclass, field
from typing import Any, Sequence

from bench.engine.store import PsuReading
from bench.interfaces import AxisState, ChamberStatus, GyroFrame, ProbeReading


@dataclass
class MemoryRun:
    plan: dict[str, Any]
    summary: dict[str, Any]
    created_t: float
    status: str = "created"
    status_history: list[tuple[float, str, str | None]] = field(default_factory=list)
    checkpoint: dict[str, Any] | None = None
    checkpoints_saved: int = 0
    steps: dict[int, dict[str, Any]] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    frames: list[tuple[int, GyroFrame]] = field(default_factory=list)
    probes: list[tuple[float, ProbeReading]] = field(default_factory=list)
    telemetry: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    segments: list[dict[str, Any]] = field(default_factory=list)
    gaps: list[dict[str, Any]] = field(default_factory=list)
    suspensions: list[dict[str, Any]] = field(default_factory=list)
    fits: dict[int, dict[str, Any]] = field(default_factory=dict)


class MemoryRunStore:
    def __init__(self) -> None:
        self.runs: dict[str, MemoryRun] = {}
        self.units: dict[str, dict[str, str]] = {}      # multi-gyro run -> slot -> its unit's run id
        self._lock = threading.Lock()

    def add_units(self, run_id: str, units: dict[str, str]) -> None:
        """Declare ``run_id`` a multi-gyro run whose gyro in each slot records into its own run."""
        with self._lock:
            self.units[run_id] = dict(units)
            for unit_run in units.values():
                self.runs.setdefault(unit_run, MemoryRun({}, {}, 0.0))

    def unit_runs(self, run_id: str) -> dict[str, str]:
        return dict(self.units.get(run_id, {}))

    def _run(self, run_id: str) -> MemoryRun:
        try:
            return self.runs[run_id]
        except KeyError:
            raise KeyError(f"run {run_id!r} not in store") from None

    def create_run(self, run_id: str, plan: dict[str, Any], summary: dict[str, Any], t: float) -> None:
        with self._lock:
            if run_id in self.runs:
                raise ValueError(f"run {run_id!r} already exists")
            self.runs[run_id] = MemoryRun(copy.deepcopy(plan), copy.deepcopy(summary), t)

    def load_plan(self, run_id: str) -> dict[str, Any]:
        return copy.deepcopy(self._run(run_id).plan)

    def set_run_status(self, run_id: str, status: str, t: float, reason: str | None = None) -> None:
        run = self._run(run_id)
        run.status = status
        run.status_history.append((t, status, reason))

    def save_checkpoint(self, run_id: str, checkpoint: dict[str, Any]) -> None:
        run = self._run(run_id)
        run.checkpoint = copy.deepcopy(checkpoint)
        run.checkpoints_saved += 1

    def load_checkpoint(self, run_id: str) -> dict[str, Any] | None:
        cp = self._run(run_id).checkpoint
        return copy.deepcopy(cp) if cp is not None else None

    def set_step_status(self, run_id: str, index: int, kind: str, status: str, t: float,
                        info: dict[str, Any] | None = None) -> None:
        row = self._run(run_id).steps.setdefault(index, {"kind": kind, "history": []})
        row["status"] = status
        row["history"].append((t, status, copy.deepcopy(info)))

    def add_event(self, run_id: str, t: float, level: str, kind: str, message: str,
                  data: dict[str, Any] | None = None) -> None:
        self._run(run_id).events.append(
            {"t": t, "level": level, "kind": kind, "message": message, "data": copy.deepcopy(data)})

    def add_frames(self, run_id: str, frames: Sequence[GyroFrame]) -> None:
        with self._lock:
            run = self._run(run_id)
            start = len(run.frames)
            run.frames.extend((start + i, f) for i, f in enumerate(frames))

    def last_frame_time(self, run_id: str) -> float | None:
        frames = self._run(run_id).frames
        return frames[-1][1].host_time if frames else None

    def add_probe_readings(self, run_id: str, t: float, readings: Sequence[ProbeReading]) -> None:
        self._run(run_id).probes.extend((t, r) for r in readings)

    def add_telemetry(self, run_id: str, t: float, chamber: ChamberStatus | None,
                      turntable: dict[int, AxisState] | None, psu: PsuReading | None) -> None:
        self._run(run_id).telemetry.append((t, {"chamber": chamber, "turntable": dict(turntable or {}) or None,
                                                "psu": psu}))

    def add_segment(self, run_id: str, step_index: int, kind: str, t_from: float, t_to: float,
                    labels: dict[str, Any]) -> None:
        self._run(run_id).segments.append({"step_index": step_index, "kind": kind, "t_from": t_from,
                                           "t_to": t_to, "labels": copy.deepcopy(labels)})

    def add_gap(self, run_id: str, t_from: float, t_to: float, reason: str,
                frames_missing: int | None = None) -> None:
        gap = {"t_from": t_from, "t_to": t_to, "reason": reason}
        if frames_missing is not None:
            gap["frames_missing"] = frames_missing
        self._run(run_id).gaps.append(gap)

    def open_suspension(self, run_id: str, t_from: float, reason: str) -> int:
        run = self._run(run_id)
        run.suspensions.append({"t_from": t_from, "t_to": None, "reason": reason})
        return len(run.suspensions) - 1

    def close_suspension(self, run_id: str, suspension_id: Any, t_to: float, reason: str) -> None:
        row = self._run(run_id).suspensions[int(suspension_id)]
        row["t_to"] = t_to
        row["reason"] = reason

    def save_fit(self, run_id: str, step_index: int, result: dict[str, Any]) -> None:
        self._run(run_id).fits[step_index] = copy.deepcopy(result)

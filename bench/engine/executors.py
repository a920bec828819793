"""One executor per step kind: issue the step's commands, advance with *active* bench time (time
that is neither paused nor suspended), say when the step is done, and give/take the state a
checkpoint needs to continue the step after a crash.  An executor sees only its ``StepContext``
(``bench.engine.context``), never the engine.

Recording steps label their active time as segments: each uninterrupted stretch is a "piece"
(pause, suspension and crash each end a piece); ``finish`` hands one segment per piece, with the
step's labels plus ``piece`` and ``complete``, to ``StepContext.record_segment``.
"""
from __future__ import annotations

from typing import Any

from bench.engine.context import StepContext
from bench.engine.orientation import solve_angles
from bench.engine.safe import angle_error, command_table_move
from bench.engine.steps import (Fit, GyroPower, Orient, Ramp, Record, SetChamber, Soak, TableRate,
                                WaitStable, step_labels)
from bench.errors import BenchError, DeviceError


class StepFailed(BenchError):
    """A step could not do what it must (table did not reach its position, PSU did not switch...)."""


class StepExecutor:
    fine = True   # wants the fine loop tick

    def __init__(self, ctx: StepContext, index: int, step: Any, estimate_s: float,
                 state: dict[str, Any] | None) -> None:
        self.ctx = ctx
        self.index = index
        self.step = step
        self.estimate_s = estimate_s
        self.resumed = state is not None
        self.saved = dict(state or {})
        self.elapsed = float(self.saved.get("elapsed_s", 0.0))
        labels = step_labels(step)
        if labels is not None and step.part:
            labels = {"part": step.part, **labels}
        self.labels = labels
        self.pieces: list[list[float]] = [list(p) for p in self.saved.get("pieces", [])]
        self.piece_start: float | None = None
        self.held = False
        self.failed_reason: str | None = None

    # ---- lifecycle --------------------------------------------------------------------------
    @property
    def records(self) -> bool:
        return self.labels is not None

    def start(self, now: float) -> None:
        self.begin(now)
        if self.records:
            self.piece_start = now

    def hold(self, now: float) -> None:
        self.held = True
        self._close_piece(now)
        self.on_hold(now)

    def release(self, now: float) -> None:
        self.held = False
        if self.records:
            self.piece_start = now
        self.on_release(now)

    def _close_piece(self, now: float) -> None:
        if self.piece_start is not None:
            if now > self.piece_start:
                self.pieces.append([self.piece_start, now])
            self.piece_start = None

    def finish(self, now: float, complete: bool) -> None:
        self._close_piece(now)
        if self.labels is None:
            return
        for k, (t_from, t_to) in enumerate(self.pieces):
            self.ctx.record_segment(self.index, self.step.kind, t_from, t_to,
                                    {**self.labels, "piece": k, "complete": complete})

    def state(self, now: float) -> dict[str, Any]:
        pieces = [list(p) for p in self.pieces]
        if self.piece_start is not None and now > self.piece_start:
            pieces.append([self.piece_start, now])
        return {"elapsed_s": self.elapsed, "pieces": pieces, **self.extra_state()}

    # ---- per kind -----------------------------------------------------------------------------
    def begin(self, now: float) -> None:
        pass

    def update(self, now: float, dt: float) -> bool:
        return True

    def deadline(self, now: float) -> float | None:
        return None

    def remaining_s(self) -> float:
        return max(0.0, self.estimate_s - self.elapsed)

    def extra_state(self) -> dict[str, Any]:
        return {}

    def on_hold(self, now: float) -> None:
        pass

    def on_release(self, now: float) -> None:
        pass


class SetChamberExec(StepExecutor):
    step: SetChamber

    def begin(self, now: float) -> None:
        hw = self.ctx.hw
        if hw.chamber_ramp is not None:
            self.ctx.devices.chamber.stop()
            hw.chamber_ramp = None
        self.ctx.devices.chamber.set_setpoint(self.step.setpoint_c)
        hw.chamber_setpoint_c = self.step.setpoint_c


class TimedExec(StepExecutor):
    """Soak and Record: a fixed amount of active bench time."""

    step: Soak | Record

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.fine = self.records

    def update(self, now: float, dt: float) -> bool:
        self.elapsed += dt
        return self.elapsed >= self.step.duration_s - 1e-9

    def deadline(self, now: float) -> float | None:
        return now + max(0.0, self.step.duration_s - self.elapsed)

    def remaining_s(self) -> float:
        return max(0.0, self.step.duration_s - self.elapsed)


class RampExec(StepExecutor):
    """Ramp the chamber; on resume re-issue the ramp from the current chamber temperature."""

    step: Ramp

    def begin(self, now: float) -> None:
        ctx, step = self.ctx, self.step
        chamber = ctx.devices.chamber
        self.phase = self.saved.get("phase", "ramp")
        self.until_elapsed = float(self.saved.get("until_elapsed_s", 0.0))
        if self.phase == "ramp":
            if self.resumed:
                start = chamber.read_temperature()
                chamber.set_setpoint(start)
                ctx.log("info", "ramp_reissued", f"ramp re-issued from the current chamber temperature "
                        f"{start:.2f} C to {step.target_c:g} C at {step.rate_c_per_min:g} C/min",
                        from_c=start, target_c=step.target_c)
                self.elapsed = 0.0
            else:
                start = (ctx.hw.chamber_setpoint_c if ctx.hw.chamber_setpoint_c is not None
                         else chamber.read_setpoint())
            chamber.ramp_to(step.target_c, step.rate_c_per_min)
            self.start_c = float(start)
            self.planned_s = abs(step.target_c - start) / step.rate_c_per_min * 60.0
            ctx.hw.chamber_ramp = {"target_c": step.target_c, "rate_c_per_min": step.rate_c_per_min}
        else:   # resumed in the until-phase: the ramp itself is over
            self.start_c = float(self.saved.get("start_c", step.target_c))
            self.planned_s = float(self.saved.get("planned_s", 0.0))
            chamber.set_setpoint(step.target_c)
            ctx.hw.chamber_ramp = None
            ctx.hw.chamber_setpoint_c = step.target_c
        self.rising = step.target_c >= self.start_c

    def extra_state(self) -> dict[str, Any]:
        return {"phase": self.phase, "until_elapsed_s": self.until_elapsed, "start_c": self.start_c,
                "planned_s": self.planned_s}

    def update(self, now: float, dt: float) -> bool:
        ctx, step, cfg = self.ctx, self.step, self.ctx.engine_config
        if self.phase == "ramp":
            self.elapsed += dt
            if self.elapsed < self.planned_s:
                return False
            status = ctx.readings.read_chamber(now)
            ramp_sp = status.ramp_setpoint_c if status is not None else None
            reached = status is not None and (ramp_sp is None or abs(ramp_sp - step.target_c) <= cfg.ramp_done_tol_c)
            late = self.elapsed >= self.planned_s * 1.1 + cfg.ramp_grace_s
            if not (reached or late):
                return False
            if not reached:
                ctx.log("warning", "ramp_late", f"chamber ramp set point {ramp_sp} C had not reached "
                        f"{step.target_c:g} C {self.elapsed - self.planned_s:.0f} s after the planned end; going on")
            ctx.hw.chamber_ramp = None
            ctx.hw.chamber_setpoint_c = step.target_c
            if step.until_probes_c is None:
                return True
            self.phase = "until"
            return False
        self.until_elapsed += dt
        values = ctx.readings.latest_probes()
        if values and all(v is not None for v in values.values()):
            goal, tol = step.until_probes_c, step.probe_tol_c
            if all((v >= goal - tol) if self.rising else (v <= goal + tol) for v in values.values()):
                ctx.log("info", "probes_reached", f"every probe reached {goal:g} C", probes=values)
                return True
        if self.until_elapsed >= step.until_timeout_s:
            ctx.log("warning", "probes_not_reached", f"probes did not all reach {step.until_probes_c:g} C "
                    f"within {step.until_timeout_s:g} s after the ramp; going on", probes=values)
            return True
        return False

    def remaining_s(self) -> float:
        extra = max(0.0, self.estimate_s - self.planned_s) if self.step.until_probes_c is not None else 0.0
        if self.phase == "ramp":
            return max(0.0, self.planned_s - self.elapsed) + extra
        return max(0.0, extra - self.until_elapsed)

    def on_hold(self, now: float) -> None:
        if self.phase == "ramp":
            try:
                self.ctx.devices.chamber.hold()
                self.ctx.log("info", "ramp_held", "chamber ramp held")
            except DeviceError as exc:
                self.ctx.log("error", "ramp_hold_failed", f"could not hold the chamber ramp: {exc}")

    def on_release(self, now: float) -> None:
        if self.phase == "ramp":
            self.ctx.devices.chamber.resume()
            self.ctx.log("info", "ramp_resumed", "chamber ramp resumed")


class WaitStableExec(StepExecutor):
    step: WaitStable

    def begin(self, now: float) -> None:
        self.stable_since: float | None = None
        self._checked: tuple[int, float | None] | None = None
        self._last_ok = False

    def _stable_now(self, now: float) -> bool:
        """Evaluated only when new probe or chamber data arrived since the last check."""
        key = (self.ctx.readings.probe_reads, self.ctx.readings.status_t)
        if key != self._checked:
            self._checked = key
            self._last_ok = self._evaluate(now)
        return self._last_ok

    def _evaluate(self, now: float) -> bool:
        step, hw, acq = self.step, self.ctx.hw, self.ctx.readings
        sp = hw.chamber_setpoint_c
        status = acq.status
        if sp is None or status is None or abs(status.pv_c - sp) > step.tol_c:
            return False
        names = acq.probe_names
        latest = acq.latest_probes()
        if step.probe_tol_c is not None:
            if not names or any(latest.get(n) is None or abs(latest[n] - sp) > step.probe_tol_c for n in names):
                return False
        if step.probe_rate_c_per_min is not None:
            if not names:
                return False
            for name in names:
                rate = acq.probe_rate_c_per_min(name, now, step.rate_window_s)
                if rate is None or abs(rate) >= step.probe_rate_c_per_min:
                    return False
        return True

    def update(self, now: float, dt: float) -> bool:
        step = self.step
        self.elapsed += dt
        if self._stable_now(now):
            if self.stable_since is None:
                self.stable_since = now
            if now - self.stable_since >= step.stable_s:
                self.ctx.log("info", "stable", f"stable for {step.stable_s:g} s after {self.elapsed:.0f} s")
                return True
        else:
            self.stable_since = None
        if self.elapsed >= step.timeout_s:
            message = f"not stable within {step.timeout_s:g} s ({step.describe()})"
            if step.on_timeout == "abort":
                raise StepFailed(f"step {self.index}: {message}")
            self.ctx.log("warning", "stable_timeout", message + "; going on")
            return True
        return False

    def on_release(self, now: float) -> None:
        self.stable_since = None
        self._checked = None


class OrientExec(StepExecutor):
    step: Orient

    def begin(self, now: float) -> None:
        ctx = self.ctx
        outer, inner = solve_angles(self.step.code, ctx.config.turntable.geometry)
        self.target = (float(outer), float(inner))
        command_table_move(ctx.devices, ctx.config, *self.target)
        ctx.hw.orientation = self.step.code.upper()
        ctx.hw.table_angles = list(self.target)
        ctx.hw.table_rates = {}

    def update(self, now: float, dt: float) -> bool:
        ctx = self.ctx
        self.elapsed += dt
        geo, tol = ctx.config.turntable.geometry, ctx.config.turntable.position_tolerance_deg
        a = ctx.devices.turntable.read(geo.outer_axis_number)
        b = ctx.devices.turntable.read(geo.inner_axis_number)
        if (angle_error(a.position_deg, self.target[0]) <= tol and angle_error(b.position_deg, self.target[1]) <= tol
                and abs(a.rate_dps) < 0.1 and abs(b.rate_dps) < 0.1):
            return True
        if self.elapsed >= self.step.timeout_s:
            raise StepFailed(f"step {self.index}: turntable did not reach {self.step.code} "
                             f"(outer {self.target[0]:g}, inner {self.target[1]:g} deg) within "
                             f"{self.step.timeout_s:g} s; at outer {a.position_deg:g}, inner {b.position_deg:g}")
        return False


class TableRateExec(StepExecutor):
    step: TableRate

    def begin(self, now: float) -> None:
        ctx = self.ctx
        geo = ctx.config.turntable.geometry
        axis = geo.outer_axis_number if self.step.axis == "outer" else geo.inner_axis_number
        ctx.devices.turntable.rate(axis, self.step.rate_dps)
        ctx.hw.orientation = None
        ctx.hw.table_rates[self.step.axis] = self.step.rate_dps


class GyroPowerExec(StepExecutor):
    step: GyroPower

    def begin(self, now: float) -> None:
        ctx, on = self.ctx, self.step.on
        ctx.devices.psu.output(on)
        if ctx.devices.psu.output_state() != on:
            raise StepFailed(f"step {self.index}: power supply output did not switch {'on' if on else 'off'}")
        ctx.hw.gyro_power = on
        ctx.gyro_powered(now, on)


class FitExec(StepExecutor):
    step: Fit

    def begin(self, now: float) -> None:
        ctx = self.ctx
        if ctx.fit is None:
            result: dict[str, Any] = {"status": "fit pending", "models": list(self.step.models),
                                      "options": dict(self.step.options)}
            ctx.log("info", "fit_pending", f"fit {', '.join(self.step.models)} pending (no fit hook wired)")
        else:
            try:
                result = dict(ctx.fit(self.index, self.step))
                result.setdefault("status", "done")
            except Exception as exc:  # noqa: BLE001 - a failed fit must not lose the recorded run
                self.failed_reason = f"{type(exc).__name__}: {exc}"
                result = {"status": "failed", "models": list(self.step.models), "error": self.failed_reason}
                ctx.log("error", "fit_failed", f"fit failed: {self.failed_reason}")
        ctx.save_fit(self.index, result)


EXECUTORS: dict[str, type[StepExecutor]] = {
    "set_chamber": SetChamberExec,
    "ramp": RampExec,
    "soak": TimedExec,
    "record": TimedExec,
    "wait_stable": WaitStableExec,
    "orient": OrientExec,
    "table_rate": TableRateExec,
    "gyro_power": GyroPowerExec,
    "fit": FitExec,
}

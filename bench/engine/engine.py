"""The run engine: executes a validated ``Plan`` on a ``Devices`` bundle, persisting through a
``RunStore`` and timing everything with a ``Clock`` (bench seconds).

Loop (one tick): drain gyro frames, read probes / telemetry when due (``Acquisition``), poll the
control, update suspension, advance the current step with *active* time (not paused, not
suspended), checkpoint when due, sleep until the next tick.  The tick is adaptive: ``tick_s`` while
recording / ramping / waiting for stability / moving, ``max_tick_s`` in plain soaks, shortened to
land on a step's end and on the next scheduled probe read or telemetry (``Acquisition.next_due``: the
acquisition schedule is a fixed bench-time grid, so on the simulated bench's lockstep clock every
device is read exactly at its period); data is drained on every tick.

Control: ``stop`` (status "stopping") finishes the current recording step (stops at once in any
other step, or when paused / suspended), then safe state, final status "stopped"; ``abort`` goes to
safe state now ("aborted"); ``pause``/``resume``.  Errors end the run as "failed" (safe state too).

Suspension: any condition from ``Acquisition.conditions`` (its suspenders, ``bench.engine.suspenders``)
suspends the run (the step's clock stops, a ramp is held, the recording piece ends); once every
condition has been clear for ``settle_s`` the run resumes (the state: ``suspenders.Suspension``).  Total suspension above ``suspension_cap_s`` aborts to safe state.

Checkpoint (``RunStore.save_checkpoint``) after each step and every ``checkpoint_period_s``::

    {"version": 1, "step_index": i, "step_state": {...} | None, "hardware": {...}, "t": bench_s,
     "suspended_total_s": s, "open_suspension": {"id", "t_from", "reason"} | None,
     "stop_requested": bool, "started_t": bench_s, "progress": {...}, "finished": status | None}

With a ``bench_state`` (the simulated bench: ``snapshot()`` / ``restore(snap)``) each checkpoint also
holds ``"bench_state"``, the bench's physical state, and ``"wall_time"``.  On a lockstep clock,
``resume`` first puts that state back at the checkpoint's bench instant and lets the outage pass in
bench time (``clock.outage_bench_s`` of the wall outage), so the chamber and the gyro continue where
they were instead of starting again from room temperature.

``resume(run_id)`` records the interruption as a gap, restores the commanded hardware state
(gyro power, table orientation or rates, chamber set point; a ramp is re-issued from the current
temperature by the ramp step) and continues the interrupted step with its remaining time.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Protocol

from bench.clock import Clock
from bench.config import BenchConfig
from bench.engine.config import EngineConfig
from bench.engine.context import HardwareState, StepContext
from bench.engine.control import COMMANDS, Control, NoControl
from bench.engine.devices import Devices
from bench.engine.executors import EXECUTORS, StepExecutor, StepFailed
from bench.engine.fixture import FixtureAcquisition
from bench.engine.monitor import Acquisition
from bench.engine.orientation import solve_angles
from bench.engine.outcomes import RunOutcome, StepOutcome
from bench.engine.planning import plan_summary, step_estimates, validate_plan
from bench.engine.safe import enter_safe_state, move_table_and_wait
from bench.engine.steps import Fit, Plan, Ramp
from bench.engine.store import RunStore
from bench.engine.suspenders import Suspension
from bench.errors import BenchError, DeviceError

FitHook = Callable[[str, int, Fit, RunStore], dict[str, Any]]


class BenchState(Protocol):
    """A simulated bench's physical state for checkpoints (``bench.sim.bench.SimulatedBench``)."""

    def snapshot(self) -> dict[str, Any]: ...
    def restore(self, snap: dict[str, Any]) -> float: ...
CHECKPOINT_VERSION = 1
MIN_SLEEP_S = 1e-3


class RunEnded(Exception):
    """Internal: the run leaves the step loop with ``status`` for ``reason``."""

    def __init__(self, status: RunOutcome, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


class Engine:
    def __init__(self, devices: Devices, store: RunStore, clock: Clock, config: BenchConfig,
                 control: Control | None = None, engine_config: EngineConfig | None = None,
                 fit_hook: FitHook | None = None, bench_state: BenchState | None = None) -> None:
        self.devices = devices
        self.store = store
        self.clock = clock
        self.config = config
        self.control = control or NoControl()
        self.cfg = engine_config or EngineConfig()
        self.fit_hook = fit_hook
        self.bench_state = bench_state
        self.run_id = ""
        self.plan: Plan | None = None
        self.estimates: list[float] = []
        self.hw = HardwareState()
        self.acq: Acquisition | FixtureAcquisition
        self.fixture: FixtureAcquisition | None = None       # several gyros in one chamber
        self.current: StepExecutor | None = None
        self.current_index = 0
        self.ended_in_step_s = 0.0     # the part of its estimate a step ended early (stop, abort) had done
        self.powered_since: float | None = None
        self.paused = False
        self.stop_requested = False
        self.suspension: Suspension | None = None
        self.suspended_closed_s = 0.0
        self.started_t = 0.0
        self.next_checkpoint = 0.0
        self.status = "created"

    # ---- public API ---------------------------------------------------------------------------
    def run(self, run_id: str, plan: Plan) -> str:
        """Validate ``plan`` (PlanError before any hardware is touched), then execute it.
        Returns the final run status."""
        summary = plan_summary(plan, self.config, self.cfg)
        now = self.clock.now()
        self._setup(run_id, plan, now)
        self.store.create_run(run_id, plan.to_json(), summary, now)
        self.started_t = now
        self._status("running", now)
        self.log("info", "run_started", f"run {run_id} started: {plan.name}, {len(plan.steps)} steps, "
                 f"about {summary['total_bench_h']:.2f} h", total_bench_s=summary["total_bench_s"])
        return self._guarded(lambda: self._start_hardware(resumed=False), 0, None)

    def resume(self, run_id: str) -> str:
        """Continue ``run_id`` from its last checkpoint (after a crash or kill -9)."""
        plan = Plan.from_json(self.store.load_plan(run_id))
        validate_plan(plan, self.config)
        cp = self.store.load_checkpoint(run_id)
        if cp is None:
            raise BenchError(f"run {run_id}: no checkpoint stored; nothing to resume")
        if cp.get("version") != CHECKPOINT_VERSION:
            raise BenchError(f"run {run_id}: checkpoint version {cp.get('version')!r} is not {CHECKPOINT_VERSION}")
        if cp.get("finished"):
            raise BenchError(f"run {run_id} already ended ({cp['finished']}); nothing to resume")
        self._restore_bench(cp)
        now = self.clock.now()
        self._setup(run_id, plan, now)
        self.hw = HardwareState.from_json(cp["hardware"])
        self.started_t = float(cp.get("started_t", cp["t"]))
        self.stop_requested = bool(cp.get("stop_requested", False))
        self.suspended_closed_s = float(cp.get("suspended_total_s", 0.0))
        last_t = float(cp["t"])
        opened = cp.get("open_suspension")
        if opened:
            self.store.close_suspension(run_id, opened["id"], last_t, opened["reason"] + " (run interrupted)")
        gap_from = _gap_start(last_t, self.store.last_frame_time(run_id))
        if self.fixture is None:
            self.store.add_gap(run_id, gap_from, now, "engine interrupted")
        else:
            # the parent has no frames to close its gap with: a row of its own; each unit's closes at its next frame
            self.store.add_gap(run_id, gap_from, now, "engine interrupted", frames_missing=0)
            self.fixture.restore(cp.get("units"))
            self.fixture.add_gap(lambda unit_run: _gap_start(last_t, self.store.last_frame_time(unit_run)), now,
                                 "engine interrupted")
        index = int(cp["step_index"])
        self._status("running", now)
        self.log("warning", "run_resumed", f"run {run_id} resumed at step {index} after an interruption of "
                 f"{now - gap_from:.0f} s", gap_from=gap_from, gap_to=now, step_index=index)
        return self._guarded(lambda: self._start_hardware(resumed=True, index=index), index,
                             cp.get("step_state"))

    def _restore_bench(self, cp: dict[str, Any]) -> None:
        """Simulated bench on a lockstep clock: its physical state back at the checkpoint, then the
        outage passes in bench time (see the module docstring)."""
        jump = getattr(self.clock, "jump_to", None)
        if jump is None:
            return
        snap = cp.get("bench_state")
        if self.bench_state is not None and snap:
            t_cp = self.bench_state.restore(snap)
            floor = t_cp
        else:
            t_cp = float(cp["t"])
            floor = max(t_cp, self.clock.now())
        outage = self.clock.outage_bench_s(time.time() - float(cp.get("wall_time", time.time())))
        jump(max(floor, t_cp + outage))

    def progress(self, now: float | None = None) -> dict[str, Any]:
        now = self.clock.now() if now is None else now
        total = sum(self.estimates)
        index = self.current_index
        done = sum(self.estimates[:index])
        remaining_later = sum(self.estimates[index + 1:])
        if self.current is not None and index < len(self.estimates):
            current_remaining = self.current.remaining_s()
            done += max(0.0, self.estimates[index] - current_remaining)
        else:
            current_remaining = 0.0
            if index < len(self.estimates):
                done += self.ended_in_step_s
        remaining = current_remaining + remaining_later
        return {
            "step_index": index,
            "n_steps": len(self.estimates),
            "step_kind": self.plan.steps[index].kind if self.plan and index < len(self.plan.steps) else None,
            "percent": 100.0 * min(1.0, done / total) if total > 0 else (100.0 if index >= len(self.estimates) else 0.0),
            "elapsed_bench_s": now - self.started_t,
            "remaining_bench_s": remaining,
            "eta_bench_t": now + remaining,
            "status": self.status,
        }

    # ---- logging / status -------------------------------------------------------------------
    def log(self, level: str, kind: str, message: str, **data: Any) -> None:
        self.store.add_event(self.run_id, self.clock.now(), level, kind, message, data or None)

    def _status(self, status: str, now: float, reason: str | None = None) -> None:
        self.status = status
        self.store.set_run_status(self.run_id, status, now, reason)
        if self.fixture is not None:
            self.fixture.set_status(status, now, reason)

    # ---- setup --------------------------------------------------------------------------------
    def _setup(self, run_id: str, plan: Plan, now: float) -> None:
        self.run_id = run_id
        self.plan = plan
        self.estimates = step_estimates(plan, self.config, self.cfg)
        self.next_checkpoint = now + self.cfg.checkpoint_period_s
        if self.devices.multi:
            units = self.store.unit_runs(run_id)
            if not units:
                raise BenchError(f"run {run_id}: this bench carries several gyros (slots "
                                 f"{', '.join(u.slot for u in self.devices.units)}) but the run names none")
            try:
                self.devices = self.devices.only(units)
            except ValueError as exc:
                raise BenchError(f"run {run_id}: {exc}") from None
            self.acq = self.fixture = FixtureAcquisition(self.devices, self.store, run_id, units, self.config,
                                                         self.cfg, self.log, now, clock_now=self.clock.now)
        else:
            self.acq = Acquisition(self.devices, self.store, run_id, self.config, self.cfg, self.log, now)

    def _start_hardware(self, resumed: bool, index: int = 0) -> None:
        dev = self.devices
        dev.gyro.start()
        dev.chamber.set_power(True)
        if self.fixture is not None:
            dev.psu.apply_unit_settings()         # PowerBank: each unit its own voltage and limit
        else:
            dev.psu.set_voltage(self.config.psu.voltage_v)
            dev.psu.set_current_limit(self.config.psu.current_limit_a)
        for axis in (self.config.turntable.geometry.outer_axis_number, self.config.turntable.geometry.inner_axis_number):
            dev.turntable.interlock_close(axis)
        self.log("info", "hardware_ready", f"gyro link started, chamber power on, PSU "
                 f"{self.config.psu.voltage_v:g} V / {self.config.psu.current_limit_a:g} A limit, table interlocks closed")
        if resumed:
            self._restore_hardware(index)

    def _restore_hardware(self, index: int) -> None:
        hw, dev, now = self.hw, self.devices, self.clock.now()
        assert self.plan is not None
        if hw.gyro_power is not None:
            dev.psu.output(hw.gyro_power)
            self.powered_since = now if hw.gyro_power else None
            self.log("info", "restore_power", f"gyro power restored {'on' if hw.gyro_power else 'off'}")
        if hw.orientation is not None:
            outer, inner = solve_angles(hw.orientation, self.config.turntable.geometry)
            ok = move_table_and_wait(dev, self.clock, self.config, outer, inner, self.config.safe_state.timeout_s * 10)
            if not ok:
                raise StepFailed(f"resume: turntable did not return to {hw.orientation}")
            self.log("info", "restore_table", f"turntable restored to {hw.orientation}")
        else:
            geo = self.config.turntable.geometry
            for axis, rate in hw.table_rates.items():
                dev.turntable.rate(geo.outer_axis_number if axis == "outer" else geo.inner_axis_number, rate)
                self.log("info", "restore_table", f"turntable {axis} axis rate restored to {rate:g} deg/s")
        in_ramp = index < len(self.plan.steps) and isinstance(self.plan.steps[index], Ramp)
        if not in_ramp and hw.chamber_setpoint_c is not None:
            dev.chamber.set_setpoint(hw.chamber_setpoint_c)
            self.log("info", "restore_chamber", f"chamber set point restored to {hw.chamber_setpoint_c:g} C")

    # ---- the run ------------------------------------------------------------------------------
    def _guarded(self, prepare: Callable[[], None], start_index: int, step_state: dict[str, Any] | None) -> str:
        try:
            prepare()
            self._steps(start_index, step_state)
        except RunEnded as end:
            self._end(end.status, end.reason)
        except (BenchError, DeviceError) as exc:
            self._end(RunOutcome.FAILED, f"{type(exc).__name__}: {exc}")
        except KeyboardInterrupt:
            self._end(RunOutcome.ABORTED, "interrupted (KeyboardInterrupt)")
            raise
        except Exception as exc:
            self._end(RunOutcome.FAILED, f"internal error {type(exc).__name__}: {exc}")
            raise
        return self.status

    def _steps(self, start_index: int, step_state: dict[str, Any] | None) -> None:
        assert self.plan is not None
        for index in range(start_index, len(self.plan.steps)):
            self._run_step(index, step_state if index == start_index else None)
            if self.stop_requested:
                raise RunEnded(RunOutcome.STOPPED, "stop requested")
        self.current = None
        self.current_index = len(self.plan.steps)
        self._end(RunOutcome.COMPLETED, None)

    def _run_step(self, index: int, state: dict[str, Any] | None) -> None:
        assert self.plan is not None
        step = self.plan.steps[index]
        now = self.clock.now()
        ex = EXECUTORS[step.kind](self._step_context(), index, step, self.estimates[index], state)
        self.current, self.current_index = ex, index
        self.store.set_step_status(self.run_id, index, step.kind, StepOutcome.RUNNING, now,
                                   {"describe": step.describe(), "resumed": state is not None})
        ex.start(now)
        last = now
        while True:
            now = self.clock.now()
            dt, last = max(0.0, now - last), now
            self._service(now)
            held = self.paused or self.suspension is not None
            if held and not ex.held:
                ex.hold(now)
            elif not held and ex.held:
                ex.release(now)
            if not held and ex.update(now, dt):
                break
            if self.stop_requested and (not ex.records or held):
                ex.finish(now, complete=False)
                self.store.set_step_status(self.run_id, index, step.kind, StepOutcome.STOPPED, now)
                raise RunEnded(RunOutcome.STOPPED, "stop requested")
            if now >= self.next_checkpoint:
                self._checkpoint(now, index, ex.state(now))
            self._sleep(now, ex)
        ex.finish(now, complete=True)
        status = StepOutcome.FAILED if ex.failed_reason else StepOutcome.DONE
        self.store.set_step_status(self.run_id, index, step.kind, status, now,
                                   {"error": ex.failed_reason} if ex.failed_reason else None)
        self.current_index = index + 1
        self.current = None
        self.acq.flush(now)
        self._checkpoint(now, index + 1, None)

    def _step_context(self) -> StepContext:
        """What a step may see and do (``bench.engine.context``), bound to this run."""
        run_id, store, fit_hook, fixture = self.run_id, self.store, self.fit_hook, self.fixture

        def record_segment(index: int, kind: str, t_from: float, t_to: float, labels: dict[str, Any]) -> None:
            store.add_segment(run_id, index, kind, t_from, t_to, labels)
            if fixture is not None:
                fixture.add_segment(index, kind, t_from, t_to, labels)

        return StepContext(
            devices=self.devices, config=self.config, engine_config=self.cfg, hw=self.hw,
            readings=self.acq, log=self.log,
            record_segment=record_segment,
            save_fit=lambda index, result: store.save_fit(run_id, index, result),
            gyro_powered=self._gyro_powered,
            fit=None if fit_hook is None else (lambda index, step: fit_hook(run_id, index, step, store)))

    def _gyro_powered(self, now: float, on: bool) -> None:
        self.powered_since = now if on else None

    def _sleep(self, now: float, ex: StepExecutor) -> None:
        fine = ex.fine or ex.held
        wake = now + (self.cfg.tick_s if fine else self.cfg.max_tick_s)
        deadline = ex.deadline(now)
        if deadline is not None and not ex.held:
            wake = min(wake, deadline)
        wake = min(wake, self.next_checkpoint, self.acq.next_due())
        self.clock.sleep(max(MIN_SLEEP_S, wake - self.clock.now()))

    # ---- service: data, control, suspension ---------------------------------------------------
    def _service(self, now: float) -> None:
        self.acq.tick(now, self.powered_since if self.hw.gyro_power else None)
        while (command := self.control.poll()) is not None:
            self._control(command, now)
        self._supervise(now)

    def _control(self, command: str, now: float) -> None:
        if command not in COMMANDS:
            self.log("warning", "control_ignored", f"unknown control request {command!r} ignored")
            return
        self.log("info", f"control_{command}", f"operator requested {command}")
        if command == "abort":
            raise RunEnded(RunOutcome.ABORTED, "abort requested")
        if command == "stop":
            self.stop_requested = True
            if self.status == "running":
                self._status("stopping", now)
        elif command == "pause" and not self.paused:
            self.paused = True
            self._status("paused", now)
        elif command == "resume" and self.paused:
            self.paused = False
            self._status("suspended" if self.suspension else "running", now)

    def _supervise(self, now: float) -> None:
        conditions = self.acq.conditions
        susp = self.suspension
        if susp is None:
            if not conditions:
                return
            reason = "; ".join(conditions.values())
            self.suspension = Suspension.opened(self.store.open_suspension(self.run_id, now, reason), now, conditions)
            self.log("warning", "suspended", f"run suspended: {reason}")
            if not self.paused:
                self._status("suspended", now, reason)
        elif conditions:
            for text in susp.add(conditions):
                self.log("warning", "suspension_reason", f"also: {text}")
            if susp.clear_since is not None:
                self.log("warning", "suspension_recurred", "condition came back while settling")
            susp.clear_since = None
        elif susp.clear_since is None:
            susp.clear_since = now
            self.log("info", "conditions_cleared", f"conditions cleared; settling {self.cfg.settle_s:g} s")
        elif now - susp.clear_since >= self.cfg.settle_s:
            self._close_suspension(now)
            self.log("info", "unsuspended", f"run resumed after {now - susp.t_from:.0f} s suspended")
            if not self.paused:
                self._status("running", now)
            return
        total = self.suspended_total(now)
        if total > self.cfg.suspension_cap_s:
            assert self.suspension is not None
            raise RunEnded(RunOutcome.ABORTED, f"suspended for a total of {total:.0f} s, over the cap of "
                                      f"{self.cfg.suspension_cap_s:g} s; last reason: {self.suspension.reason}")

    def _close_suspension(self, now: float) -> None:
        susp = self.suspension
        if susp is not None:
            self.store.close_suspension(self.run_id, susp.id, now, susp.reason)
            self.suspended_closed_s += now - susp.t_from
            self.suspension = None

    def suspended_total(self, now: float) -> float:
        current = now - self.suspension.t_from if self.suspension else 0.0
        return self.suspended_closed_s + current

    # ---- checkpoint / end ---------------------------------------------------------------------
    def _checkpoint(self, now: float, index: int, step_state: dict[str, Any] | None,
                    finished: str | None = None) -> None:
        self.acq.flush(now)
        self.store.save_checkpoint(self.run_id, {
            "version": CHECKPOINT_VERSION,
            "step_index": index,
            "step_state": step_state,
            "hardware": self.hw.to_json(),
            "t": now,
            "started_t": self.started_t,
            "suspended_total_s": self.suspended_total(now),
            "open_suspension": self.suspension.checkpoint() if self.suspension else None,
            "stop_requested": self.stop_requested,
            "progress": self.progress(now),
            "finished": finished,
            "wall_time": time.time(),
            "bench_state": self.bench_state.snapshot() if self.bench_state is not None and not finished else None,
            "units": self.fixture.checkpoint() if self.fixture is not None else None,
        })
        self.next_checkpoint = now + self.cfg.checkpoint_period_s

    def _end(self, status: RunOutcome, reason: str | None) -> None:
        now = self.clock.now()
        ex = self.current
        if ex is not None:
            # the run's last progress keeps what the interrupted step had done (a run stopped in its soak
            # at 16 % stays at 16 %, not the 0 % of the steps before it)
            if self.current_index < len(self.estimates):
                self.ended_in_step_s = max(0.0, self.estimates[self.current_index] - ex.remaining_s())
            ex.finish(now, complete=False)
            self.store.set_step_status(self.run_id, ex.index, ex.step.kind, StepOutcome.ending_run(status),
                                       now, {"reason": reason})
            self.current = None
        self._close_suspension(now)
        try:
            self.acq.flush(now)
        except Exception as exc:  # noqa: BLE001 - still reach the safe state
            self.log("error", "flush_failed", f"could not store the last frames: {exc}")
        if status != RunOutcome.COMPLETED:
            self.log("warning" if status == RunOutcome.STOPPED else "error", f"run_{status}", f"run {status}: {reason}")
        safe_ok = enter_safe_state(self.devices, self.clock, self.config, self.hw.chamber_ramp is not None, self.log)
        self.hw.chamber_ramp = None
        try:
            self.devices.gyro.stop()
        except DeviceError as exc:
            self.log("error", "link_stop_failed", f"gyro link stop failed: {exc}")
        now = self.clock.now()
        try:
            self.acq.final_reading(now)
        except Exception as exc:  # noqa: BLE001 - the run still ends and records how
            self.log("warning", "final_reading_failed", f"could not read the bench after the safe state: {exc}")
        self._checkpoint(now, self.current_index, None, finished=status)
        if self.fixture is not None:
            reason = self.fixture.finish(status, now, reason)
        self._status(status, now, reason if safe_ok else f"{reason or status}; safe state incomplete")
        self.log("info", "run_ended", f"run ended: {status}", safe_state_ok=safe_ok)


def _gap_start(last_checkpoint_t: float, last_frame_t: float | None) -> float:
    """Where the outage of an interrupted run starts: its last checkpoint, or its last stored frame if later."""
    return max(last_checkpoint_t, last_frame_t) if last_frame_t is not None else last_checkpoint_t

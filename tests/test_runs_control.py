"""Abort (the simulators end in the safe state), a chamber alarm (suspends, resumes once cleared) and
bad plans (refused before anything is created or moved), on the simulated bench with the real
drivers, the engine and ``SqlRunStore``.

The simulated bench runs in lockstep (``bench.clock.LockstepClock``, as fast as the host can) and the
test holds its bench time at known instants while it looks and acts: what the run is doing there does
not depend on the host's load."""
from __future__ import annotations

import threading

import pytest
from sqlalchemy import select

import procedures
from bench.engine import Engine, QueueControl
from bench.engine.factory import build_devices, close_devices, engine_config_for, make_fit_hook
from bench.engine.sqlstore import SqlRunStore, new_run, run_report
from bench.sim.bench import SimulatedBench, lockstep_clock
from bench.storage.db import open_database
from bench.storage.models import Event, Run, Segment
from tests.service_support import SAFETY_S, hold_clock_at, hold_clock_until
from tests.test_runs_support import cli


class SimRun:
    """A procedure on an in-process simulated bench in lockstep, engine in a thread (the clock's driver),
    so the test can hold bench time and act meanwhile."""

    def __init__(self, url: str, procedure: str, **params) -> None:
        self.clock = lockstep_clock(None, seed=0)
        self.bench = SimulatedBench(clock=self.clock, seed=0, data_rate_hz=1).start()
        self.config = self.bench.config
        self.db = open_database(url)
        module = procedures.get(procedure)
        self.plan = module.build(module.Params(**params))
        self.engine_config = engine_config_for(self.bench.clock)
        self.run_id = new_run(self.db, procedure=procedure, parameters=params, gyro_id="C1",
                              config_snapshot=self.config.model_dump(mode="json"), bench_name=self.config.name,
                              launch={"engine_config": self.engine_config.model_dump()})
        self.store = SqlRunStore(self.db, geometry=self.config.turntable.geometry,
                                 nominal_rate_hz=self.config.gyro.data_rate_hz)
        self.devices = build_devices(self.config, self.bench.clock)
        self.control = QueueControl()
        self.engine = Engine(self.devices, self.store, self.bench.clock, self.config, self.control,
                             self.engine_config, make_fit_hook(self.db, self.store, latitude_deg=45.0))
        self.status: str | None = None
        self.thread = threading.Thread(target=self._go, daemon=True)
        self.t0 = self.clock.now()
        self.clock.hold_at(self.t0)              # nothing moves until the test holds it further on

    def _go(self) -> None:
        self.status = self.engine.run(str(self.run_id), self.plan)

    def start(self) -> "SimRun":
        self.thread.start()
        return self

    def ended(self) -> bool:
        return not self.thread.is_alive()

    def hold_at(self, t: float) -> None:
        hold_clock_at(self.clock, t, self.ended)

    def hold_until(self, predicate, what: str, step_s: float = 10.0, limit_s: float = 4 * 3600.0) -> float:
        """Hold every ``step_s`` bench seconds until ``predicate()`` holds there (``what``)."""
        try:
            return hold_clock_until(self.clock, predicate, step_s, limit_s, self.ended)
        except AssertionError as exc:
            raise AssertionError(f"waiting for {what}: {exc} (run status {self.status})") from None

    def finish(self, timeout_s: float = SAFETY_S) -> str:
        self.clock.release()
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), "engine did not finish"
        self.store.close(self.run_id)
        return self.status

    def close(self) -> None:
        self.clock.release()
        self.thread.join(SAFETY_S)
        close_devices(self.devices)
        self.bench.stop()
        self.db.dispose()


@pytest.fixture
def url(tmp_path):
    return f"sqlite:///{tmp_path / 'bench.sqlite'}"


def test_abort_mid_ramp_leaves_the_simulators_in_the_safe_state(url):
    # WSU: outer axis at 180 deg, so parking at (0, 0) is a real move; ramp 30 -> 15 C
    r = SimRun(url, "thermal_ramp", orientation="WSU", start_c=30.0, soak_h=0.01, warmup_min=0.5,
               rate_c_per_min=1.0, end_c=15.0, final_hold_min=1.0).start()
    try:
        r.hold_until(lambda: r.engine.current is not None and r.engine.current.step.kind == "ramp"
                     and r.engine.current.elapsed > 60.0, "the ramp")
        assert r.bench.chamber_model.mode == 2            # the chamber runs its ramp profile
        assert r.bench.psu_model.output_on
        assert abs(r.bench.table_model.angles()[0]) == pytest.approx(180.0, abs=0.05)
        r.control.request("abort")                        # taken at the engine's next tick
        assert r.finish() == "aborted"
        cfg = r.config.safe_state
        chamber, table, psu = r.bench.chamber_model, r.bench.table_model, r.bench.psu_model
        chamber.advance_to(r.bench.clock.now())
        assert chamber.mode == 0 and chamber.setpoint_c == pytest.approx(cfg.chamber_setpoint_c, abs=0.05)
        table.advance_to(r.bench.clock.now())
        assert [abs(v) for v in table.rates()] == [0.0, 0.0]
        assert table.angles()[0] == pytest.approx(cfg.park_outer_deg, abs=0.05)
        assert table.angles()[1] == pytest.approx(cfg.park_inner_deg, abs=0.05)
        assert psu.output_on is False
        with r.db.session() as s:
            run = s.get(Run, r.run_id)
            kinds = {e.kind: (e.data or {}).get("level") for e in s.scalars(select(Event).where(Event.run_id == r.run_id))}
        assert run.status == "aborted" and "abort requested" in run.error and "incomplete" not in run.error
        # each safe-state action was confirmed within safe_state.timeout_s (logged as info, not error)
        assert kinds["safe_chamber"] == kinds["safe_table"] == kinds["safe_power"] == "info"
    finally:
        r.close()


def test_chamber_alarm_suspends_and_the_run_resumes_after_it_clears(url):
    r = SimRun(url, "thermal_ramp", start_c=26.0, soak_h=0.01, warmup_min=4.0, rate_c_per_min=2.0,
               end_c=24.0, final_hold_min=1.0).start()
    try:
        t = r.hold_until(lambda: r.engine.current is not None and r.engine.current.records
                         and r.engine.current.elapsed > 30.0, "the warm-up recording")
        r.bench.chamber_model.inject_alarm(2)             # high deviation alarm, forced
        r.hold_at(t + 60.0)                               # the chamber is read every 5 bench s
        assert r.engine.suspension is not None
        assert _stored_status(r) == "suspended"
        r.hold_at(t + 60.0 + 2 * r.engine_config.settle_s)  # stays suspended while the alarm is latched
        assert r.engine.suspension is not None and _stored_status(r) == "suspended"
        r.bench.chamber_model.inject_alarm(0)             # condition gone ...
        r.bench.chamber_model.clear_alarm()               # ... and acknowledged at the panel (register 312)
        assert r.finish() == "completed"
        report = run_report(r.db, r.run_id)
        assert report["status"] == "completed" and len(report["suspensions"]) == 1
        sus = report["suspensions"][0]
        assert "chamber alarm 2" in sus["reason"] and sus["t_to"] is not None
        assert sus["duration_s"] >= r.engine_config.settle_s
        with r.db.session() as s:
            warmup = [sg for sg in s.scalars(select(Segment).where(Segment.run_id == r.run_id)
                                             .order_by(Segment.t_start)) if sg.labels["phase"] == "warmup"]
        # the recording stopped while suspended: two pieces, none overlapping the suspension
        assert len(warmup) == 2
        assert warmup[0].t_end <= sus["t_from"] + 1e-6 and warmup[1].t_start >= sus["t_to"] - 1e-6
    finally:
        r.close()


@pytest.mark.parametrize("params, message", [
    (["points_c=[20,100]"], "set point 100 C is outside the allowed range"),
    (['positions=["ESD","XYZ"]'], "'XYZ' has letters"),
    (["soak_h=-1"], "--param soak_h: Input should be greater than 0"),
    (["bogus=1"], "--param bogus: Extra inputs are not permitted"),
])
def test_bad_eight_position_plans_are_refused(url, params, message):
    args = ["run", "eight_position", "--gyro", "B1", "--sim", "--speed", "600", "--db", url]
    for p in params:
        args += ["--param", p]
    code, out, err = cli(args)
    assert code == 2 and message in err and "run " not in out
    _no_runs(url)


@pytest.mark.parametrize("params, message", [
    (["rate_c_per_min=10"], "ramp rate 10 C/min exceeds the chamber maximum 5 C/min"),
    (["orientation=NUE"], "the turntable cannot reach NUE"),
    (["orientation=NUS"], "not a right-handed triad"),
])
def test_bad_thermal_ramp_plans_are_refused(url, params, message):
    args = ["run", "thermal_ramp", "--gyro", "B1", "--sim", "--db", url]
    for p in params:
        args += ["--param", p]
    code, out, err = cli(args)
    assert code == 2 and message in err, err
    _no_runs(url)


def test_run_without_config_or_sim_is_refused(url, monkeypatch):
    monkeypatch.delenv("BENCH_CONFIG", raising=False)
    code, _, err = cli(["run", "thermal_ramp", "--gyro", "B1", "--db", url])
    assert code == 2 and "no bench config" in err
    code, _, err = cli(["run", "nine_position", "--gyro", "B1", "--sim", "--db", url])
    assert code == 2 and "unknown procedure 'nine_position'" in err


def _stored_status(r: SimRun) -> str:
    with r.db.session() as s:
        return s.get(Run, r.run_id).status


def _no_runs(url: str) -> None:
    db = open_database(url)
    try:
        with db.session() as s:
            assert s.scalars(select(Run)).first() is None
    finally:
        db.dispose()

"""Kill -9 of a ``bench worker`` driving the simulated bench mid-run: a new worker for the bench takes
the run over (stale heartbeat), restores the hardware and completes it; the outage is a recorded gap.

The simulated bench runs in this process on an accelerated clock (the worker in another process drives
it over its transports, so its time cannot be held).  The run is held instead: a chamber alarm raised
before it starts keeps it suspended (steps not advancing, checkpoints still taken) until the test clears
it under the second worker, so the kill lands mid-run however loaded the host (the engine's suspension
cap, 4 bench hours, is minutes of wall time at x60)."""
from __future__ import annotations

from bench.sim.bench import SimulatedBench
from bench.storage import open_database, queries
from tests.api_support import SHORT_RAMP
from tests.service_support import Services


def _worker(services: Services, tmp):
    return services.worker("--bench", "simk", "--config", str(tmp / "endpoints.json"), "--heartbeat", "0.2",
                           "--stale-after", "1.5", "--poll", "0.05", log="w.log")


def _run(db, rid):
    with db.session() as s:
        return queries.get_run(s, rid)


def test_killed_worker_on_the_simulated_bench_is_taken_over_and_the_run_completes(tmp_path):
    url = f"sqlite:///{tmp_path / 'k.sqlite'}"
    db = open_database(url)
    sim = SimulatedBench(speed=60.0, bench_name="simk").start()
    try:
        with Services(tmp_path, BENCH_DATABASE_URL=url) as services:
            sim.write_endpoints(tmp_path / "endpoints.json")
            sim.chamber_model.inject_alarm(2)
            first = _worker(services, tmp_path)
            with db.session() as s:
                rid = queries.create_run(s, procedure="thermal_ramp", bench_name="simk", gyro_id="SIMK",
                                         parameters=dict(SHORT_RAMP, orientation=None, soak_h=0.02, warmup_min=0.5,
                                                         end_c=26.0, final_hold_min=0.5)).id
            # until it is suspended on the alarm with a checkpoint stored
            services.wait_for(lambda: (r := _run(db, rid)).status == "suspended" and r.checkpoint is not None,
                              "the run suspended with a checkpoint", first, interval=0.2)
            first_id = _run(db, rid).worker
            services.kill(first)
            second = _worker(services, tmp_path)
            services.wait_for(lambda: _run(db, rid).worker not in (None, first_id),
                              "the second worker taking the run over", second, interval=0.2)
            chamber = sim.chamber_model
            chamber.inject_alarm(0)                 # condition gone; acknowledged once the air is in band
            services.wait_for(lambda: chamber.clear_alarm() or chamber.alarm == 0, "the alarm cleared", second)
            run = services.wait_for(lambda: (r := _run(db, rid)).status in ("completed", "failed", "aborted") and r,
                                    "the run to end under the second worker", second, interval=0.3)
            assert run.status == "completed", (run.status, run.error, services.log_of(second).read_text()[-3000:])
            with db.session() as s:
                kinds = [e.kind for e in queries.list_events(s, rid)]
                gaps = queries.list_gaps(s, rid)
            assert "worker_takeover" in kinds and "run_resumed" in kinds
            assert gaps, "the outage must be recorded as a gap"
    finally:
        sim.stop()
        db.dispose()

"""Kill -9 of a ``bench worker`` driving the simulated bench mid-run: a new worker for the bench takes
the run over (stale heartbeat), restores the hardware and completes it; the outage is a recorded gap."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from bench.sim.bench import SimulatedBench
from bench.storage import open_database, queries
from tests.api_support import SHORT_RAMP
from tests.service_support import SAFETY_S


def _worker(tmp, env):
    return subprocess.Popen([sys.executable, "-m", "bench.cli", "worker", "--bench", "simk", "--config",
                             str(tmp / "endpoints.json"), "--heartbeat", "0.2", "--stale-after", "1.5",
                             "--poll", "0.05"], env=env, cwd=tmp, stdout=open(tmp / "w.log", "ab"),
                            stderr=subprocess.STDOUT)


def test_killed_worker_on_the_simulated_bench_is_taken_over_and_the_run_completes(tmp_path):
    url = f"sqlite:///{tmp_path / 'k.sqlite'}"
    db = open_database(url)
    sim = SimulatedBench(speed=60.0, bench_name="simk").start()
    env = {**os.environ, "BENCH_DATABASE_URL": url}
    first = second = None
    try:
        sim.write_endpoints(tmp_path / "endpoints.json")
        first = _worker(tmp_path, env)
        with db.session() as s:
            rid = queries.create_run(s, procedure="thermal_ramp", bench_name="simk", gyro_id="SIMK",
                                     parameters=dict(SHORT_RAMP, orientation=None, soak_h=0.1)).id
        deadline = time.monotonic() + SAFETY_S
        while time.monotonic() < deadline:                 # wait until it is running with frames stored
            with db.session() as s:
                run = queries.get_run(s, rid)
                if run.status == "running" and run.progress > 0.2:
                    break
            time.sleep(0.2)
        else:
            raise AssertionError(f"run never got going: {(tmp_path / 'w.log').read_text()[-2000:]}")
        first.send_signal(signal.SIGKILL)
        first.wait()
        second = _worker(tmp_path, env)
        deadline = time.monotonic() + SAFETY_S
        while time.monotonic() < deadline:
            with db.session() as s:
                run = queries.get_run(s, rid)
                if run.status in ("completed", "failed", "aborted"):
                    break
            time.sleep(0.3)
        assert run.status == "completed", (run.status, run.error, (tmp_path / "w.log").read_text()[-3000:])
        with db.session() as s:
            kinds = [e.kind for e in queries.list_events(s, rid)]
            gaps = queries.list_gaps(s, rid)
        assert "worker_takeover" in kinds and "run_resumed" in kinds
        assert gaps, "the outage must be recorded as a gap"
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=20)
        sim.stop()
        db.dispose()

"""Lockstep bench time across processes: ``bench sim up`` (the simulators) in one process, ``bench run
--sim-endpoints`` (the engine) in another, driving the simulators' clock over the clock endpoint
(``bench.clocklink``).  The same scenario and ``--seed`` record the same measured data at x600 and at
``--speed max``; the link's protocol and its errors are checked on an in-process clock."""
from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

import pytest

from bench.clock import LockstepClock, clock_from_json
from bench.clocklink import LINK_KIND, ClockLinkServer, attach
from bench.errors import LinkDown, ProtocolError
from tests.service_support import PY, SAFETY_S, Services
from tests.test_runs_support import cli, last_json

SHORT = ["start_c=30", "soak_h=0.05", "warmup_min=5", "rate_c_per_min=1", "end_c=22", "final_hold_min=5"]


def _sim_up(services: Services, endpoints: Path, log: str, seed: int = 7) -> subprocess.Popen:
    proc = services.spawn([PY, "-m", "bench.cli", "sim", "up", "--seed", str(seed), "--endpoints-json",
                           str(endpoints)], log)
    services.wait_for(lambda: endpoints.exists(), "bench sim up to write its endpoints file", proc)
    return proc


def _bench(args: list[str]) -> str:
    """``bench ARGS`` in this process (the engine's process; the simulators run in ``bench sim up``)."""
    code, out, err = cli(args)
    assert code == 0, (args, out[-2000:], err[-3000:])
    return out


def _ramp(args: list[str], url: str) -> tuple[list[str], dict]:
    """A short thermal ramp on the bench ``args`` name; its measured-data CSV lines and ``runs show``."""
    for p in SHORT:
        args += ["--param", p]
    run = last_json(_bench(["run", "thermal_ramp", "--gyro", "L1", *args, "--json", "--no-progress", "--db", url]))
    assert run["status"] == "completed", run
    csv = _bench(["export", str(run["run_id"]), "--format", "csv", "--db", url])
    return csv.splitlines(), json.loads(_bench(["runs", "show", str(run["run_id"]), "--json", "--db", url]))


def _record(services: Services, tmp: Path, name: str, speed: str) -> tuple[list[str], dict]:
    """The short ramp on a fresh ``bench sim up --seed 7``, driven at ``speed``."""
    endpoints = tmp / f"{name}-endpoints.json"
    sim = _sim_up(services, endpoints, f"{name}-sim.log")
    doc = json.loads(endpoints.read_text())
    assert doc["clock"]["kind"] == LINK_KIND and doc["seed"] == 7
    got = _ramp(["--sim-endpoints", str(endpoints), "--speed", speed], f"sqlite:///{tmp / (name + '.sqlite')}")
    services.stop(sim)
    assert sim.returncode == 0, services.log_of(sim).read_text()[-2000:]
    return got


def _same(a: list[str], b: list[str]) -> None:
    diff = [(i, x, y) for i, (x, y) in enumerate(zip(a, b)) if x != y]
    assert len(a) == len(b) and not diff, (len(a), len(b), diff[:3])


def test_sim_up_seed_records_the_same_csv_at_x600_and_at_max(tmp_path):
    with Services(tmp_path) as services:
        paced, show = _record(services, tmp_path, "x600", "600")
        fast, _ = _record(services, tmp_path, "max", "max")
    # and the same as with the simulated bench in the engine's own process
    in_process, _ = _ramp(["--sim", "--seed", "7", "--speed", "max"], f"sqlite:///{tmp_path / 'inproc.sqlite'}")
    assert len(paced) > 800
    _same(paced, fast)
    _same(paced, in_process)
    # sampled at the real bench-time rates although the simulators run in another process
    sampling = show["sampling"]
    assert sampling["probes"]["readings"] > 100 and sampling["probes"]["max_interval_s"] <= 2.0
    assert sampling["chamber"]["max_interval_s"] <= 5.0
    assert sampling["gyro"]["median_interval_s"] == pytest.approx(1.0)
    assert sampling["gyro"]["max_interval_s"] <= 1.0 + 1e-6


def test_run_fails_clearly_when_the_sim_process_is_gone(tmp_path):
    with Services(tmp_path) as services:
        endpoints = tmp_path / "endpoints.json"
        sim = _sim_up(services, endpoints, "sim.log")
        services.stop(sim)
    code, _out, err = cli(["run", "thermal_ramp", "--gyro", "L1", "--sim-endpoints", str(endpoints),
                           "--no-progress", "--db", f"sqlite:///{tmp_path / 'gone.sqlite'}"])
    assert code != 0
    assert "simulated bench clock at 127.0.0.1:" in err and "bench sim up" in err, err[-2000:]


# ---- the link on an in-process clock ---------------------------------------------------------------
class _Counter:
    """A participant: serves each instant once and reports it (as the gyro line reports bytes)."""

    def __init__(self) -> None:
        self.served: list[float] = []

    def __call__(self, t: float) -> dict:
        self.served.append(t)
        return {"t": t, "n": len(self.served)}


@pytest.fixture
def served_clock():
    clock = LockstepClock(1000.0, None)
    first, second = _Counter(), _Counter()
    clock.serve("first", first)
    clock.serve("second", second)
    server = ClockLinkServer(clock).start()
    try:
        yield clock, server, first, second
    finally:
        server.stop()


def test_driving_clock_serves_every_instant_in_the_other_clock(served_clock):
    clock, server, first, second = served_clock
    driving = clock_from_json({**server.to_json(None), "pace": None})
    assert driving.now() == 1000.0 and driving.participants() == ["first", "second"]
    got = []
    driving.receive("check", lambda t, reports: got.append((t, reports, clock.now())))
    driving.sleep(2.0)
    driving.advance_to(1003.5)
    assert first.served == [1002.0, 1003.5] and second.served == [1002.0, 1003.5]
    assert clock.now() == 1003.5
    # receivers run after the other process served the instant, with its reports
    assert got[0] == (1002.0, {"first": {"t": 1002.0, "n": 1}, "second": {"t": 1002.0, "n": 1}}, 1002.0)
    driving.serve_now()                   # serving the same instant again (a driver that connected since)
    assert first.served[-1] == 1003.5 and len(first.served) == 3
    driving.link.close()


def test_link_refuses_a_second_driver_going_back_and_bad_requests(served_clock):
    clock, server, _first, _second = served_clock
    driving = attach(server.address, None)
    with pytest.raises(LinkDown, match="busy: another process drives"):
        attach(server.address, None)
    driving.sleep(10.0)
    with pytest.raises(ProtocolError, match="cannot go back"):
        driving.link.advance(1005.0)
    assert server.handle("ADVANCE soon").startswith("ERR ADVANCE needs a bench time")
    assert server.handle("JUMP 5").startswith("ERR unknown request")
    driving.link.close()
    # the first driver gone, another may drive from where it stopped
    again = attach(server.address, None)
    assert again.now() == 1010.0
    again.link.close()


def test_link_down_names_the_endpoint_when_the_simulator_process_is_gone(served_clock):
    _clock, server, _first, _second = served_clock
    address = server.address
    driving = attach(address, None)
    server.stop()
    with pytest.raises(LinkDown, match=f"simulated bench clock at {address}: .*bench sim up"):
        driving.sleep(1.0)
    with pytest.raises(LinkDown, match="bench sim up"):       # and at once on every later instant
        driving.sleep(1.0)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    with pytest.raises(LinkDown, match=f"127.0.0.1:{free}: cannot connect"):
        attach(f"127.0.0.1:{free}", None)


def test_engine_killed_at_a_hold_then_resumed_on_the_same_sim_process(tmp_path):
    """The engine's process holds the bench time (``BENCH_SIM_HOLD_FILE``, on the driving side) mid-ramp,
    is killed -9 there, and ``bench resume`` drives the same ``bench sim up`` on: the simulator kept its
    physical state, so the chamber and probes continue across the stated outage."""
    from sqlalchemy import select

    from bench.storage.db import open_database
    from bench.storage.models import Gap
    from tests.test_runs_resume import HOLD_T, OUTAGE_S, PARAMS, _assert_continuous, _wait_held_mid_ramp

    url = f"sqlite:///{tmp_path / 'k.sqlite'}"
    hold = tmp_path / "hold"
    hold.write_text(repr(HOLD_T))
    with Services(tmp_path) as services:
        endpoints = tmp_path / "endpoints.json"
        sim = _sim_up(services, endpoints, "sim.log", seed=1)
        args = [PY, "-m", "bench.cli", "run", "thermal_ramp", "--gyro", "K1", "--sim-endpoints", str(endpoints),
                "--speed", "200", "--no-progress", "--db", url]
        for p in PARAMS:
            args += ["--param", p]
        run = services.spawn(args, "run.log", BENCH_SIM_HOLD_FILE=str(hold))
        services.wait_for(lambda: "run 1" in services.log_of(run).read_text(), "the run to be created", run)
        db = open_database(url)
        _wait_held_mid_ramp(db, 1, run, hold, timeout_s=SAFETY_S)
        services.kill(run)
        code, out, err = cli(["resume", "1", "--db", url, "--json", "--no-progress", "--outage", str(OUTAGE_S)])
        doc = last_json(out)
        assert code == 0 and doc["status"] == "completed", (doc, err[-3000:])
        assert sim.poll() is None                   # the same simulator process all along
    with db.session() as s:
        gaps = [g for g in s.scalars(select(Gap).where(Gap.run_id == 1)) if g.reason == "crash_resume"]
    assert len(gaps) == 1 and gaps[0].t_to >= HOLD_T
    _assert_continuous(db, 1, gaps[0])
    db.dispose()

"""SIGSTOP drill with real processes, on SQLite and PostgreSQL: two ``bench worker`` processes for one
simulated bench (the simulators run in this test's process).  Worker A drives a run; it is frozen with
SIGSTOP past its lease; worker B takes the run over; A is woken with SIGCONT while B drives.  The run
ends ``completed``, A leaves its run loop, every frame index is stored once, and the simulators' own
request logs (``bench.sim.audit``) show that nothing reached any device on A's links after B took over.

Links: A's are those that sent requests before B was started (A reaches the chamber over Modbus TCP, B
over Modbus RTU); B's are those first seen between B's start and the SIGCONT (A is stopped then).  Any
request after the takeover on a link that is not B's counts as A's.  The test waits on states (run
claimed, taken over, ended; A's log), never on a duration.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from sqlalchemy import select

from bench.sim.bench import SimulatedBench
from bench.storage import open_database, queries
from bench.storage.models import Event, FrameChunk
from tests.api_support import SHORT_RAMP, unique_bench

SPEED = 60.0
DEADLINE_S = 240.0          # a loaded 2-core machine; the drill waits on states


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'sigstop.sqlite'}"
    return request.getfixturevalue("pg_url")


def _worker(tmp, name: str, config: str, log: str, db_url: str) -> subprocess.Popen:
    env = {**os.environ, "BENCH_DATABASE_URL": db_url}
    return subprocess.Popen([sys.executable, "-m", "bench", "worker", "--bench", name, "--config", str(tmp / config),
                             "--no-jobs", "--heartbeat", "0.2", "--stale-after", "1.5", "--poll", "0.05",
                             "--log-level", "info"], env=env, cwd=tmp, stdout=open(tmp / log, "ab"),
                            stderr=subprocess.STDOUT)


def _wait(predicate, what: str, logs=()):
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    tails = "\n".join(f"--- {p.name}:\n{p.read_text()[-2000:]}" for p in logs if p.exists())
    raise AssertionError(f"timed out waiting for {what}\n{tails}")


def _run(db, rid):
    with db.session() as s:
        run = queries.get_run(s, rid)
        s.expunge(run)
        return run


def test_sigstop_owner_past_its_lease_then_sigcont_sends_nothing_and_the_run_completes(db_url, tmp_path):
    name = unique_bench()
    db = open_database(db_url)
    sim = SimulatedBench(speed=SPEED, bench_name=name).start()
    logs = (tmp_path / "a.log", tmp_path / "b.log")
    a = b = None
    try:
        sim.write_endpoints(tmp_path / "a.json")
        doc = json.loads((tmp_path / "a.json").read_text())
        doc["bench_config"]["chamber"].update(transport="modbus_rtu", address=sim.endpoints["chamber_modbus_rtu"])
        (tmp_path / "b.json").write_text(json.dumps(doc))
        a = _worker(tmp_path, name, "a.json", "a.log", db_url)
        with db.session() as s:
            rid = queries.create_run(s, procedure="thermal_ramp", bench_name=name, gyro_id="SIGSTOP",
                                     parameters=dict(SHORT_RAMP, orientation=None, soak_h=0.3)).id
        run = _wait(lambda: (r := _run(db, rid)).status == "running" and r.progress > 0.05 and r,
                    "worker A driving the run", logs)
        a_id = run.worker
        a.send_signal(signal.SIGSTOP)
        b_started = time.monotonic()
        b = _worker(tmp_path, name, "b.json", "b.log", db_url)
        run = _wait(lambda: (r := _run(db, rid)).worker not in (None, a_id) and r, "worker B taking over", logs)
        taken_over = time.monotonic()
        b_id = run.worker

        def b_links_now() -> set[str]:
            seen = sim.received()
            return {e.link for e in seen if e.mono >= b_started} - {e.link for e in seen if e.mono < b_started}

        # B restores the hardware over its own links (chamber RTU, turntable, power supply) before A wakes
        _wait(lambda: "modbus_rtu" in (links := b_links_now()) and len(links) >= 3, "worker B driving", logs)
        active_at_wake = _run(db, rid).status in queries.ACTIVE
        a.send_signal(signal.SIGCONT)
        woken = time.monotonic()
        _wait(lambda: "leaving the run loop" in logs[0].read_text(), "worker A leaving its run loop", logs)
        run = _wait(lambda: (r := _run(db, rid)).status in queries.TERMINAL and r, "the run to end", logs)
        assert run.status == "completed", (run.status, run.error)
        assert run.worker == b_id and run.error is None
        assert active_at_wake, "B had finished before A woke: the drill did not test a wake during B's run"
        received = sim.received()
        a_links = {e.link for e in received if e.mono < b_started}
        b_links = {e.link for e in received if b_started <= e.mono < woken} - a_links
        assert "modbus_tcp" in a_links and len(a_links) >= 3, f"A drove the hardware: {sorted(a_links)}"
        assert "modbus_rtu" in b_links, f"B drove the hardware: {sorted(b_links)}"
        late = [e for e in received if e.mono >= taken_over and e.link not in b_links]
        assert not late, f"requests from worker A after the takeover: {late[:10]}"
        assert any(e.link in b_links and e.mono >= woken for e in received), "B went on driving after A woke"
        with db.session() as s:
            chunks = s.execute(select(FrameChunk.first_index, FrameChunk.count).where(FrameChunk.run_id == rid)
                               .order_by(FrameChunk.first_index)).all()
            kinds = [e.kind for e in s.scalars(select(Event).where(Event.run_id == rid))]
        expected = 0
        for first_index, count in chunks:                     # every frame index stored exactly once
            assert first_index == expected
            expected += count
        assert expected > 0 and "worker_takeover" in kinds and "run_failed" not in kinds
    finally:
        for proc in (a, b):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        sim.stop()
        db.dispose()

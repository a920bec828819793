"""SIGSTOP drill with real processes, on SQLite and PostgreSQL: two ``bench worker`` processes for one
simulated bench (the simulators run in this test's process).  Worker A drives a run; it is frozen with
SIGSTOP past its lease; worker B takes the run over; A is woken with SIGCONT while B drives.  The run
ends ``completed``, A leaves its run loop, every frame index is stored once, and the simulators' own
request logs (``bench.sim.audit``) show that nothing reached any device on A's links after B took over.

Links: A's are those that sent requests before B was started (A reaches the chamber over Modbus TCP, B
over Modbus RTU); B's are those first seen between B's start and the SIGCONT (A is stopped then).  Any
request after the takeover on a link that is not B's counts as A's.  The test waits on states (run
claimed, suspended, taken over, ended; A's log), never on a duration.

The workers drive the simulators from other processes, so bench time (an accelerated clock) cannot be
held.  The run is held instead: a chamber alarm, raised before the run starts, keeps it suspended (active,
its steps not advancing) from A's first reading until the test clears it, after A woke and left.  So B
is still driving when A wakes however slow the host is; the only wall limit is the engine's suspension
cap (4 bench hours: minutes of wall time at x60).  A is stopped at a moment it holds no database lock
(checked after each SIGSTOP, else woken and stopped again): a process stopped inside a transaction
blocks every other writer of an SQLite file, and the rows it locked on PostgreSQL, so B could never
take over; that is the database's limit, not the fencing this drill is about.  Once A has left its run loop it is stopped: a woken
worker may legitimately take a run back whose heartbeat went stale on a loaded host, which is not this
drill's question.
"""
from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
from sqlalchemy import select

from bench.sim.bench import SimulatedBench
from bench.storage import open_database, queries
from bench.storage.models import Event, FrameChunk
from tests.api_support import SHORT_RAMP, unique_bench
from tests.service_support import Services

SPEED = 60.0
DEADLINE_S = 240.0          # a loaded 2-core machine; the drill waits on states


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'sigstop.sqlite'}"
    return request.getfixturevalue("pg_url")


def _worker(services: Services, name: str, config: str, log: str) -> subprocess.Popen:
    return services.worker("--bench", name, "--config", str(services.tmp / config), "--no-jobs", "--heartbeat",
                           "0.2", "--stale-after", "3", "--poll", "0.05", "--log-level", "info", log=log)


def _wait(predicate, what: str, logs=()):
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    tails = "\n".join(f"--- {p.name}:\n{p.read_text()[-2000:]}" for p in logs if p.exists())
    raise AssertionError(f"timed out waiting for {what}\n{tails}")


def _holds_no_lock(db, rid: int, bench: str) -> bool:
    """Whether another process could write the run's rows now: SQLite's write lock is free, or the run's,
    the bench's and the frame cursor's rows are not locked on PostgreSQL."""
    from sqlalchemy import text
    from sqlalchemy.exc import OperationalError

    if db.dialect == "sqlite":
        import sqlite3

        conn = sqlite3.connect(db.engine.url.database, timeout=0, isolation_level=None)
        try:
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("ROLLBACK")
            return True
        except sqlite3.OperationalError:
            return False
        finally:
            conn.close()
    try:
        with db.engine.connect() as conn:
            with conn.begin() as tx:
                for sql in ("SELECT id FROM runs WHERE id = :rid FOR UPDATE NOWAIT",
                            "SELECT id FROM benches WHERE name = :bench FOR UPDATE NOWAIT",
                            "SELECT run_id FROM frame_cursors WHERE run_id = :rid FOR UPDATE NOWAIT"):
                    conn.execute(text(sql), {"rid": rid, "bench": bench})
                tx.rollback()
        return True
    except OperationalError:
        return False


def _stop_outside_transactions(proc: subprocess.Popen, db, rid: int, bench: str) -> int:
    """SIGSTOP ``proc`` at a moment it holds no lock of the run (see the module docstring); attempts made."""
    for attempt in range(1, 1001):
        proc.send_signal(signal.SIGSTOP)
        if _holds_no_lock(db, rid, bench):
            return attempt
        proc.send_signal(signal.SIGCONT)
        time.sleep(0.01)
    raise AssertionError("worker A held a database lock at each of 1000 stops")


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
    services = Services(tmp_path, BENCH_DATABASE_URL=db_url)
    a = b = None
    try:
        sim.write_endpoints(tmp_path / "a.json")
        doc = json.loads((tmp_path / "a.json").read_text())
        doc["bench_config"]["chamber"].update(transport="modbus_rtu", address=sim.endpoints["chamber_modbus_rtu"])
        (tmp_path / "b.json").write_text(json.dumps(doc))
        sim.chamber_model.inject_alarm(2)            # the run will be suspended from its first chamber reading
        a = _worker(services, name, "a.json", "a.log")
        with db.session() as s:
            rid = queries.create_run(s, procedure="thermal_ramp", bench_name=name, gyro_id="SIGSTOP",
                                     parameters=dict(SHORT_RAMP, orientation=None, soak_h=0.02, warmup_min=0.5,
                                                     end_c=26.0, final_hold_min=0.5)).id
        run = _wait(lambda: (r := _run(db, rid)).status == "suspended" and r, "worker A driving the run, suspended",
                    logs)
        a_id = run.worker
        _stop_outside_transactions(a, db, rid, name)
        b_started = time.monotonic()
        b = _worker(services, name, "b.json", "b.log")
        run = _wait(lambda: (r := _run(db, rid)).worker not in (None, a_id) and r, "worker B taking over", logs)
        taken_over = time.monotonic()
        b_id = run.worker

        def b_links_now() -> set[str]:
            seen = sim.received()
            return {e.link for e in seen if e.mono >= b_started} - {e.link for e in seen if e.mono < b_started}

        # B restores the hardware over its own links (chamber RTU, turntable, power supply) and finds the
        # alarm again before A wakes
        _wait(lambda: "modbus_rtu" in (links := b_links_now()) and len(links) >= 3, "worker B driving", logs)
        _wait(lambda: _run(db, rid).status == "suspended", "the run suspended under worker B", logs)
        a.send_signal(signal.SIGCONT)
        woken = time.monotonic()
        _wait(lambda: "leaving the run loop" in logs[0].read_text(), "worker A leaving its run loop", logs)
        services.stop(a)
        assert _run(db, rid).status == "suspended"    # B's run still held when A left
        left = time.monotonic()
        _wait(lambda: any(e.link == "modbus_rtu" and e.mono >= left for e in sim.received()),
              "worker B reading the chamber after A left", logs)
        chamber = sim.chamber_model
        chamber.inject_alarm(0)                      # condition gone; acknowledged once the air is in band
        _wait(lambda: chamber.clear_alarm() or chamber.alarm == 0, "the chamber alarm cleared", logs)
        run = _wait(lambda: (r := _run(db, rid)).status in queries.TERMINAL and r, "the run to end", logs)
        assert run.status == "completed", (run.status, run.error)
        assert run.worker == b_id and run.error is None
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
        assert "suspended" in kinds and "unsuspended" in kinds
    finally:
        for proc in (a, b):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGCONT)          # a stopped process cannot act on SIGTERM
        services.close()
        sim.stop()
        db.dispose()

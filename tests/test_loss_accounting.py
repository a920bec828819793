"""Honest loss accounting end to end: the gyro simulator corrupts 1 % of the bytes on a real TCP line,
the driver (GyroSerialLink) takes the intact frames off it, the frame writer stores them (SQLite and
PostgreSQL).  The gap rows' frames_missing add up to what the simulator knows the line lost, and the
stored times strictly increase although the link stamps each read with one host time."""
from __future__ import annotations

import numpy as np
import pytest

from bench.clock import SteppedClock
from bench.storage import FrameWriter, open_database, queries, read_frames
from bench.sim.gyro import GyroStreamSimulator
from tests.test_gyro_link import T0, RampSource, collect, make, wait_until

SECONDS = 30


@pytest.fixture(params=["sqlite", "postgresql"])
def db(request, tmp_path):
    url = (f"sqlite:///{tmp_path / 'loss.sqlite'}" if request.param == "sqlite"
           else request.getfixturevalue("pg_url"))
    database = open_database(url)
    yield database
    database.dispose()


def test_one_percent_corruption_frames_missing_match_what_the_line_lost(db):
    clock = SteppedClock(T0)
    sim, link = make(clock, sent_log_limit=10 ** 6)
    sim.faults.corrupt_rate = 0.01
    with db.session() as s:
        run_id = queries.create_run(s, procedure="loss-drill", gyro_id="G-LOSS").id
    got = []
    try:
        for _ in range(SECONDS):
            clock.advance(1.0)
            wait_until(lambda: sim.sent_count() >= round((clock.now() - T0) * 1000), what="sim output")
            # every intact frame of this second received (and so stamped) before the clock moves on: the
            # drill measures the accounting, not how late a loaded host reads its line
            intact_so_far = sum(1 for f in sim.sent_frames() if not f.corrupted)
            wait_until(lambda: len(got) + link.pending() >= intact_so_far, what="link input")
            got += link.drain()
        sent = sim.sent_frames()
        intact = sum(1 for s in sent if not s.corrupted)
        got += collect(link, intact - len(got)) if len(got) < intact else []
    finally:
        link.stop()
        sim.stop()
    assert len(sent) == SECONDS * 1000 and len(got) == intact
    lost_by_sim, span, gaps, counted = _store_and_count(db, run_id, sent, got)
    print(f"\n{db.dialect}: line lost {lost_by_sim} of {span} frames; gap rows count {counted} "
          f"in {len(gaps)} rows")
    assert all(g.frames_missing is not None and g.frames_missing > 0 for g in gaps)
    assert {g.reason for g in gaps} == {"corruption"}
    assert abs(counted - lost_by_sim) <= 0.01 * lost_by_sim
    times = np.asarray(read_frames(db, run_id).time)
    assert np.all(np.diff(times) > 0)                  # no two stored frames share a time
    true_t = np.array([s.bench_time for s in sent if not s.corrupted])
    err = np.abs(times - true_t)
    print(f"stored time - true time: median {np.median(err) * 1e3:.1f} ms, max {err.max() * 1e3:.0f} ms")
    assert err.max() < 1.5      # bench s: the test's clock steps 1 s at a time, a read is stamped after a step


class LateHost:
    """A host that reads the gyro line late and in pieces, on the bench clock: the test's own socket
    takes every byte the simulator wrote for a clock step, but hands them to the frame decoder only when
    the seeded plan says the host gets to read (0.25 to 2.5 bench s late some of the time), split into up
    to three reads that all carry the same host stamp - as a busy host does."""

    STEP_S = 0.25

    def __init__(self, clock, sim, seed: int) -> None:
        import socket

        from bench.devices.kvh import FrameDecoder

        self.clock, self.sim = clock, sim
        self.rng = np.random.default_rng(seed)
        self.sock = socket.create_connection(sim.address, timeout=5)
        wait_until(lambda: sim.client_connected, what="simulator accepted the host")
        self.decoder = FrameDecoder("kvh_a")
        self.received = bytearray()
        self.read_upto = 0          # bytes of ``received`` the host has read (decoded)
        self.late_until = clock.now()
        self.frames = []

    def step(self) -> None:
        self.clock.advance(self.STEP_S)
        due = round((self.clock.now() - T0) * 1000)
        wait_until(lambda: self.sim.sent_count() >= due, what="sim output")
        size = self.sim.sent_count() * self.decoder.spec.length
        while len(self.received) < size:
            self.received += self.sock.recv(1 << 20)
        if self.clock.now() < self.late_until:
            return                                           # the host is busy elsewhere
        self.read_all()
        if self.rng.random() < 0.15:
            self.late_until = self.clock.now() + self.STEP_S * self.rng.integers(1, 11)

    def read_all(self) -> None:
        backlog = bytes(self.received[self.read_upto:])
        self.read_upto = len(self.received)
        cuts = sorted(self.rng.integers(0, len(backlog) + 1, self.rng.integers(0, 3)).tolist())
        now = self.clock.now()
        for a, b in zip([0] + cuts, cuts + [len(backlog)]):
            self.frames += self.decoder.feed(backlog[a:b], now, 1e-3)

    def close(self) -> None:
        self.sock.close()


def test_frames_missing_stay_within_one_percent_when_the_host_reads_late(db):
    """Reads that come late and in pieces must not be taken for lost turns of the 7-bit counter: the
    counter and the data rate count the frames; the host clock only settles whole turns it proves."""
    clock = SteppedClock(T0)
    sim = GyroStreamSimulator(RampSource(), clock, 1000, "kvh_a", seed=7, sent_log_limit=10 ** 6)
    sim.faults.corrupt_rate = 0.01
    sim.start()
    host = LateHost(clock, sim, seed=3)
    with db.session() as s:
        run_id = queries.create_run(s, procedure="loss-drill-late", gyro_id="G-LATE").id
    try:
        for _ in range(round(SECONDS / LateHost.STEP_S)):
            host.step()
        host.read_all()
        sent = sim.sent_frames()
    finally:
        host.close()
        sim.stop()
    got = host.frames
    intact = [s for s in sent if not s.corrupted]
    assert [f.raw for f in got] == [s.frame for s in intact]
    lost_by_sim, span, gaps, counted = _store_and_count(db, run_id, sent, got)
    print(f"\n{db.dialect}, host reading late: line lost {lost_by_sim} of {span} frames; gap rows "
          f"count {counted} in {len(gaps)} rows")
    assert {g.reason for g in gaps} == {"corruption"}
    assert abs(counted - lost_by_sim) <= 0.01 * lost_by_sim
    times = np.asarray(read_frames(db, run_id).time)
    assert np.all(np.diff(times) > 0)


def _store_and_count(db, run_id, sent, got):
    """Store the received frames and compare: the frames the simulator corrupted between the first and
    last intact one (what the line lost), the span, the gap rows and the sum of their frames_missing."""
    first = next(k for k, s in enumerate(sent) if not s.corrupted)
    last = max(k for k, s in enumerate(sent) if not s.corrupted)
    lost_by_sim = sum(1 for s in sent[first:last + 1] if s.corrupted)
    with FrameWriter(db, run_id, autostart=False, nominal_rate_hz=1000.0) as w:
        w.add_many(got)
    with db.session() as s:
        gaps = queries.list_gaps(s, run_id)
    return lost_by_sim, last - first + 1, gaps, sum(g.frames_missing for g in gaps)

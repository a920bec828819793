"""Gyro stream simulator + GyroSerialLink over a real TCP socket / pty (stepped bench clock)."""
from __future__ import annotations

import math
import re
import socket
import time

import pytest

from bench.clock import SteppedClock
from bench.config import GyroConfig
from bench.devices.gyro import GyroSerialLink
from bench.errors import LinkDown, ProtocolError
from bench.interfaces import GyroLink
from bench.sim.gyro import GyroSample, GyroStreamSimulator
from tests.service_support import SAFETY_S
from tests.test_gyro_codec import independent_decode

T0 = 1_700_000_000.0


class RampSource:
    """Deterministic test source: every value a known function of bench time (unique frames)."""

    def __init__(self) -> None:
        self.advanced: list[float] = []

    def advance_to(self, t: float) -> None:
        assert not self.advanced or t >= self.advanced[-1]
        self.advanced.append(t)

    def sample(self, t: float) -> GyroSample:
        dt = t - T0
        temp = 20.0 + 0.01 * dt
        return GyroSample((0.001 * dt, -0.5, 0.25), (0.0, 0.01, 1.0), temp,
                          (4900.0 + 0.47 * (temp - 20), 4890.0, 4700.0 + 1e-6 * dt))


def wait_until(predicate, timeout_s: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.005)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def clock():
    return SteppedClock(T0)


def make(clock, rate=1000, frame="kvh_a", transport="tcp", **kw):
    sim = GyroStreamSimulator(RampSource(), clock, rate, frame, transport=transport, **kw)
    sim.start()
    link = GyroSerialLink(GyroConfig(url=sim.url, frame=frame, data_rate_hz=rate, reconnect_s=0.05), clock)
    link.start()
    if transport == "tcp":
        wait_until(lambda: sim.client_connected, what="simulator accepted the link")
    return sim, link


def collect(link, n, timeout_s=5.0):
    got = []
    wait_until(lambda: got.extend(link.drain()) or len(got) >= n, timeout_s, f"{n} frames (have {len(got)})")
    return got


def test_every_frame_arrives_in_order(clock):
    sim, link = make(clock)
    try:
        assert isinstance(link, GyroLink)
        clock.advance(0.5)
        got = collect(link, 500)
        sent = sim.sent_frames()
        assert len(sent) == 500 and all(s.delivered for s in sent)
        assert [f.raw for f in got] == [s.frame for s in sent]
        assert [s.bench_time for s in sent] == pytest.approx([T0 + (k + 1) / 1000 for k in range(500)], abs=1e-6)
        assert got[10].gyro[0] == pytest.approx(0.001 * 0.011, abs=1e-9)   # bench t ~1.7e9: 2e-7 s steps
        assert got[10].temperature_c == pytest.approx(20.00011, abs=0.006)
        assert link.stats.frames == 500 and link.stats.bad_crc == 0 and link.stats.missing_frames == 0
        times = [f.host_time for f in got]
        assert times == sorted(times) and times[-1] <= clock.now()
        assert link.drain() == []
    finally:
        link.stop()
        sim.stop()


def test_one_percent_corruption_no_bad_frame_accepted_no_intact_frame_lost(clock):
    sim, link = make(clock)
    sim.faults.corrupt_rate = 0.01
    try:
        for _ in range(10):
            clock.advance(1.0)
            wait_until(lambda: sim.sent_count() >= round((clock.now() - T0) * 1000), what="sim output")
        sent = sim.sent_frames()
        intact = [s.frame for s in sent if not s.corrupted]
        got = collect(link, len(intact))
        time.sleep(0.05)
        got += link.drain()
        assert len(sent) == 10_000 and all(s.delivered for s in sent)
        assert 0.25 < 1 - len(intact) / len(sent) < 0.35          # 1 - 0.99**36 = 0.30
        assert [f.raw for f in got] == intact                      # nothing bad in, nothing intact out
        st = link.stats
        assert st.bad_crc > 1000 and st.resyncs > 0
        first = next(k for k, s in enumerate(sent) if not s.corrupted)
        last = max(k for k, s in enumerate(sent) if not s.corrupted)
        assert st.frames + st.missing_frames == last - first + 1
    finally:
        link.stop()
        sim.stop()


def test_independent_decoder_agrees_with_raw_stream(clock):
    sim = GyroStreamSimulator(RampSource(), clock, 500, "kvh_a")
    sim.start()
    try:
        conn = socket.create_connection(sim.address, timeout=2)
        wait_until(lambda: sim.client_connected, what="client")
        clock.advance(1.0)
        data = b""
        while len(data) < 500 * 36:
            data += conn.recv(65536)
        conn.close()
        frames = independent_decode(data)
        assert [f[5] for f in frames] == [s.frame for s in sim.sent_frames()]
        assert [f[0] for f in frames] == [k % 128 for k in range(500)]
        assert frames[99][1][0] == pytest.approx(0.001 * 0.2, rel=1e-6)   # frame 100 at t0 + 0.2 s
        assert frames[99][4] == pytest.approx(20.002, abs=0.006)
    finally:
        sim.stop()


def test_link_drop_reconnects_and_reports_gap(clock):
    sim, link = make(clock, rate=100)
    try:
        clock.advance(0.5)
        before = collect(link, 50)
        sim.faults.drop_link()
        wait_until(lambda: not link.connected, what="link loss seen")
        clock.advance(2.0)                                   # 200 frames produced into the void
        wait_until(lambda: len(sim.sent_frames()) == 250, what="frames during the gap")
        time.sleep(0.15)                                     # reconnect attempts are refused meanwhile
        assert link.stats.reconnects == 0 and not link.connected
        sim.faults.restore_link()
        wait_until(lambda: link.stats.reconnects == 1, what="reconnect")
        clock.advance(0.5)
        after = collect(link, 50)
        sent = sim.sent_frames()
        lost = [s for s in sent if not s.delivered]
        assert len(lost) == 200
        assert [f.raw for f in before + after] == [s.frame for s in sent if s.delivered]
        (gap_from, gap_to), = link.stats.link_gaps
        assert gap_from <= lost[0].bench_time and lost[-1].bench_time <= gap_to
        assert link.stats.missing_frames == 0                # decoder reset: no mod-128 guess across the gap
        assert "disconnected" in (link.last_error or "") or "refused" in (link.last_error or "")
    finally:
        link.stop()
        sim.stop()


def test_configure_data_rate_and_config_mode(clock):
    sim, link = make(clock, rate=1000)
    try:
        clock.advance(0.1)
        collect(link, 100)
        assert link.configure_data_rate(100) == 100
        assert sim.data_rate_hz == 100 and not sim.config_mode and link.data_rate_hz == 100
        assert link.query_data_rate() == 100
        n = len(sim.sent_frames())
        clock.advance(1.0)
        got = collect(link, 100)
        assert len(sim.sent_frames()) - n == 100
        assert link.stats.missing_frames == 0
        assert got[-1].host_time == pytest.approx(clock.now())
        with pytest.raises(ValueError, match="not one of"):
            link.configure_data_rate(7)
        with pytest.raises(ProtocolError, match="NOT IN CONFIG MODE"):
            link._command("=DR,250", re.compile(rb"DR,250\r\n"), 1.0)
    finally:
        link.stop()
        sim.stop()


def test_sim_command_replies_and_no_frames_in_config_mode(clock):
    sim = GyroStreamSimulator(RampSource(), clock, 1000)
    sim.start()
    try:
        assert sim.execute_command("?DR") == "DR,1000"
        assert sim.execute_command("=DR,500") == "ERROR,NOT IN CONFIG MODE"
        assert sim.execute_command("=CONFIG,1") == "CONFIG,1"
        n = len(sim.sent_frames())
        clock.advance(0.5)
        time.sleep(0.05)
        assert len(sim.sent_frames()) == n
        assert sim.execute_command("=DR,7") == "ERROR,DR 7 NOT ALLOWED"
        assert sim.execute_command("=DR,3600") == "DR,3600"
        assert sim.execute_command("=BAUD,1") .startswith("ERROR,UNKNOWN COMMAND")
        assert sim.execute_command("=CONFIG,0") == "CONFIG,0"
        clock.advance(0.01)
        wait_until(lambda: len(sim.sent_frames()) == n + 36, what="frames at 3600 Hz")
        with pytest.raises(ValueError, match="allowed set"):
            GyroStreamSimulator(RampSource(), clock, 300)
    finally:
        sim.stop()


def test_invalid_status_pause_and_rad_per_s(clock):
    sim, link = make(clock, rate=100, output_units="rad/s")
    try:
        sim.faults.clear_status_bits = 0x01
        clock.advance(0.1)
        got = collect(link, 10)
        assert all(f.status == 0x76 for f in got) and link.stats.invalid_status == 10
        assert got[0].gyro[1] == pytest.approx(-0.5 * math.pi / 180, rel=1e-6)
        sim.faults.clear_status_bits = 0
        sim.faults.paused = True
        clock.advance(1.0)
        time.sleep(0.05)
        assert len(sim.sent_frames()) == 10
        sim.faults.paused = False
        time.sleep(0.02)
        clock.advance(0.1)
        got = collect(link, 10)
        assert [f.sequence for f in got] == list(range(10, 20))   # a pause is silence, not a gap
        assert got[0].status == 0x77 and link.stats.missing_frames == 0
    finally:
        link.stop()
        sim.stop()


def test_hrg_frames_over_pty(clock):
    sim, link = make(clock, rate=100, frame="hrg", transport="pty")
    try:
        assert sim.pty_path and sim.pty_path.startswith("/dev/")
        clock.advance(0.2)
        got = collect(link, 20)
        assert [f.raw for f in got] == [s.frame for s in sim.sent_frames()]
        src = RampSource()
        assert got[4].freq_hz == src.sample(T0 + 0.05).freq_hz      # float64 frequencies: exact
        assert link.configure_data_rate(50) == 50 and sim.data_rate_hz == 50
    finally:
        link.stop()
        sim.stop()


def test_overrun_is_visible_as_sequence_gap(clock):
    sim, link = make(clock, rate=1000, max_backlog_frames=100)
    try:
        clock.advance(0.05)
        collect(link, 50)
        clock.advance(0.3)                                    # 300 due, only 100 made
        got = collect(link, 100)
        assert sim.overrun_frames == 200
        assert link.stats.sequence_gaps == 1 and link.stats.missing_frames == 200 % 128
        assert got[0].sequence == (50 + 200) % 128
    finally:
        link.stop()
        sim.stop()


def test_start_on_dead_port_raises_link_down(clock):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    link = GyroSerialLink(GyroConfig(url=f"socket://127.0.0.1:{port}"), clock)
    with pytest.raises(LinkDown, match=str(port)):
        link.start()


def test_accelerated_clock_batches_frames_at_exact_bench_times():
    from bench.clock import AcceleratedClock

    clock = AcceleratedClock(speed=50.0, bench_epoch=T0)
    sim, link = make(clock, rate=250)                       # 12 500 frames per wall second
    deadline = time.monotonic() + SAFETY_S
    try:
        got, handed_at = [], []
        while len(got) < 2001:                                  # about 0.16 wall s of frames when idle
            batch = link.drain()
            now = clock.now()
            got += batch
            handed_at += [now] * len(batch)
            assert time.monotonic() < deadline, f"timed out waiting for 2001 frames (have {len(got)})"
            time.sleep(0.005)
        sent = sim.sent_frames()
        # frames made before the link connected are lost, and pyserial's open() flushes input that
        # arrived between accept() and open() returning: the link's stream starts a little late
        delivered = [s.frame for s in sent if s.delivered]
        start = delivered.index(got[0].raw)
        assert len(got) > 2000 and start < 500
        assert [f.raw for f in got] == delivered[start:start + len(got)]
        t_first = sent[0].bench_time
        assert [s.bench_time for s in sent] == pytest.approx([t_first + k / 250 for k in range(len(sent))], abs=1e-6)
        assert link.stats.missing_frames == 0 and link.stats.bad_crc == 0
        # back-dating by the nominal period never stamps a frame before the device made it, nor after
        # the link handed it over (the bench time at the end of the drain that returned it): the stamp
        # is the receipt, however long the host took to get there
        made = {s.frame: s.bench_time for s in sent}
        assert all(made[f.raw] - 1e-6 <= f.host_time <= handed for f, handed in zip(got, handed_at))
    finally:
        link.stop()
        sim.stop()


def test_source_failure_is_reported_not_swallowed(clock):
    class Broken(RampSource):
        def sample(self, t):
            return GyroSample((1.0, 2.0), (0.0, 0.0, 1.0), 20.0)

    sim = GyroStreamSimulator(Broken(), clock, 100)
    sim.start()
    try:
        clock.advance(0.05)
        wait_until(lambda: sim.error is not None, what="simulator error")
        assert "3 rates" in str(sim.error)
    finally:
        sim.stop()


def test_lockstep_drop_lands_on_its_bench_instant_while_the_simulator_reads_commands():
    """Lockstep: a dropped line is lost at the bench instant the simulator closed it, reconnects are
    refused from that instant on, and the gap ends at the first attempt after the line is back; the
    simulator's command-reading thread selects on the same sockets all along (it holds them while it
    waits, so a plain close ended the connection, and stopped the listening, only once that thread let
    go of them: a wall-clock moment, seen as drops landing on later instants under load).  Twenty drops,
    each checked at its instant, with the clock unpaced (no wall time between instants)."""
    from bench.clock import LockstepClock

    clock = LockstepClock(T0, pace=None)
    sim = GyroStreamSimulator(RampSource(), clock, 1, "kvh_a")
    sim.start()
    clock.serve("gyro", sim.serve)
    link = GyroSerialLink(GyroConfig(url=sim.url, data_rate_hz=1, reconnect_s=0.5), clock)
    link.start()
    try:
        t = T0
        expected = []
        for _ in range(20):
            t += 3.0
            clock.advance_to(t)
            assert link.connected and sim.client_connected
            sim.faults.drop_link(None)              # acts at the next instant the clock serves
            clock.advance_to(t + 1.0)
            assert not link.connected, f"the drop at {t + 1.0 - T0} was not seen at its instant"
            for k in range(2, 5):                   # attempts due at +1.5, +2.5, +3.5: refused
                clock.advance_to(t + k)
                assert not link.connected and not sim.client_connected
            sim.faults.restore_link()
            clock.advance_to(t + 5.0)               # listening again, the attempt due at +4.5 is made
            expected.append((t + 1.0, t + 5.0))
            assert link.stats.link_gaps == expected
            t += 5.0
        assert link.receive_timeouts == 0
        assert link.stats.reconnects == 20
    finally:
        link.stop()
        sim.stop()

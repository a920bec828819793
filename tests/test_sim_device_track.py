"""The chamber and table states a multi-gyro bench's units integrate on come from one shared
``DeviceTrack`` (``bench.sim.lookahead``): reusing it changes no served byte, at 1000 Hz frames
(instant by instant, frames between grid points) and at 1 Hz (blocks ahead), commands included."""
from __future__ import annotations

from bench.sim.bench import lockstep_clock
from bench.sim.lookahead import DeviceTrack
from bench.sim.multibench import MultiGyroBench


def _drive(rate: int, instants: int, step_s: float, shared: bool):
    clock = lockstep_clock(None, seed=5)
    bench = MultiGyroBench(units=3, clock=clock, seed=5, data_rate_hz=rate)
    if not shared:                       # each unit on a track of its own: nothing reused
        for unit in bench.units[1:]:
            unit.lookahead.bench.device_track = DeviceTrack()
    bench.start()
    try:
        probes = []
        for i in range(instants):
            clock.sleep(step_s)
            if i == 2:
                for unit in bench.units:
                    unit.psu_model.set_voltage(28.0)
                    unit.psu_model.set_output(True)
            if i == instants // 3:
                bench.chamber_model.set_setpoint(35.0)
            if i == instants // 2:
                bench.table_model.interlock_close(1)
                bench.table_model.set_mode(1, "R")
                bench.table_model.set_rate_demand(1, 10.0)
            probes.append([u.lookahead.probe_temperatures() for u in bench.units])
        frames = [[(f.bench_time, f.frame) for f in u.gyro.sent_frames()] for u in bench.units]
        tracks = {id(u.lookahead.bench.device_track): u.lookahead.bench.device_track for u in bench.units}
        return frames, probes, sum(t.reused for t in tracks.values())
    finally:
        bench.stop()


def test_a_shared_track_serves_the_bytes_of_private_ones_at_1000_hz():
    frames, probes, reused = _drive(1000, 24, 0.25, shared=True)
    own_frames, own_probes, own_reused = _drive(1000, 24, 0.25, shared=False)
    assert [len(f) for f in frames] == [6000] * 3
    assert frames == own_frames and probes == own_probes
    assert own_reused == 0 and reused >= 24           # the units after the first reuse the states
    assert frames[0] != frames[1] != frames[2]        # units differ (their own scenario draws)


def test_a_shared_track_serves_the_bytes_of_private_ones_with_blocks_ahead():
    frames, probes, reused = _drive(1, 90, 2.0, shared=True)
    own_frames, own_probes, _ = _drive(1, 90, 2.0, shared=False)
    assert [len(f) for f in frames] == [180] * 3
    assert frames == own_frames and probes == own_probes
    assert reused > 0

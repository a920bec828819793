"""The lockstep bench's gyro physics integrated in blocks ahead of the clock (``bench.sim.lookahead``):
what it serves is what an instant-by-instant integration serves, and commands given while a block
is ahead act at their own bench instant."""
from __future__ import annotations

import base64
import pickle
import zlib

import numpy as np

from bench.sim.bench import SimulatedBench, lockstep_clock
from bench.sim.lookahead import Lookahead

POWER_ON, SETPOINT, POWER_OFF = 20, 40, 90      # instants (every 2 bench seconds) of the commands


def _drive(ahead_s: float | None) -> tuple[list[tuple[float, bytes]], list[dict[str, float]], dict[str, int]]:
    clock = lockstep_clock(None, seed=3)
    bench = SimulatedBench(clock=clock, seed=3)
    if ahead_s is not None:           # 0: every block ends at the instant being served
        bench.lookahead.MIN_AHEAD_S = bench.lookahead.MAX_AHEAD_S = ahead_s
        bench.lookahead._ahead = ahead_s
    bench.start()
    try:
        probes = []
        for i in range(150):
            clock.sleep(2.0)
            if i == POWER_ON:
                bench.psu_model.set_voltage(28.0)
                bench.psu_model.set_output(True)
            if i == SETPOINT:
                bench.chamber_model.set_setpoint(40.0)
            if i == POWER_OFF:
                bench.psu_model.set_output(False)
            probes.append(bench.lookahead.probe_temperatures())
        frames = [(f.bench_time, f.frame) for f in bench.gyro.sent_frames()]
        return frames, probes, dict(bench.lookahead.stats)
    finally:
        bench.stop()


def test_blocks_ahead_serve_the_same_bytes_as_one_instant_at_a_time():
    step_frames, step_probes, _ = _drive(0.0)
    frames, probes, stats = _drive(None)
    assert len(frames) == len(step_frames) == 300
    assert frames == step_frames                       # byte for byte, bench time for bench time
    assert probes == step_probes
    # the blocks were ahead of the clock, and the three commands each dropped one
    assert stats["blocks"] < 60 and stats["dropped"] >= 3 and stats["direct"] == 0
    assert Lookahead.MAX_AHEAD_S > 2.0


def test_commands_act_at_their_instant():
    frames, probes, _ = _drive(None)
    t0 = frames[0][0] - 1.0
    # frames carry zero rate while the gyro is unpowered (bytes of the rate fields all zero)
    powered = np.array([any(frame[4:16]) for _, frame in frames])
    times = np.array([t for t, _ in frames])
    on_at, off_at = t0 + 2.0 * (POWER_ON + 1), t0 + 2.0 * (POWER_OFF + 1)
    assert not powered[times <= on_at].any()
    assert powered[(times > on_at) & (times <= off_at)].all()
    assert not powered[times > off_at].any()
    # the chamber heats towards 40 C from the set-point instant on: probes flat before, rising after
    mean = [float(np.mean(list(p.values()))) for p in probes]
    assert abs(mean[SETPOINT] - mean[0]) < 0.2
    assert mean[-1] > mean[SETPOINT] + 1.0


def _snapshots_while_driving(snapshot_every: int | None) -> tuple[list[tuple[float, bytes]], list[dict], dict[str, int]]:
    """A seeded bench driven 300 instants with the supply on; a snapshot every ``snapshot_every``
    instants (as a run's checkpoints take them), taken with the physics at the instant."""
    clock = lockstep_clock(None, seed=4)
    bench = SimulatedBench(clock=clock, seed=4).start()
    try:
        bench.psu_model.set_voltage(28.0)
        bench.psu_model.set_output(True)
        snaps = []
        for i in range(300):
            clock.sleep(2.0)
            if snapshot_every and i % snapshot_every == 0:
                snaps.append(bench.snapshot())
        frames = [(f.bench_time, f.frame) for f in bench.gyro.sent_frames()]
        return frames, snaps, dict(bench.lookahead.stats)
    finally:
        bench.stop()


def test_a_snapshot_keeps_the_block_ahead_and_changes_nothing_served():
    plain_frames, _, plain_stats = _snapshots_while_driving(None)
    frames, snaps, stats = _snapshots_while_driving(25)
    assert frames == plain_frames and len(frames) == 600
    assert stats == plain_stats                        # no block dropped nor integrated again
    assert stats["blocks"] < 20
    # each snapshot holds the physics at its own instant, not where the block ahead had got to
    for snap in snaps:
        state = pickle.loads(zlib.decompress(base64.b64decode(snap["state"])))
        assert state["physics"]["_state"].t == snap["t"]


def test_sample_rows_are_the_per_element_conversion():
    from bench.sim.physics import GyroSample, Outputs, SampleRows

    rng = np.random.default_rng(5)
    n = 40
    rate = rng.normal(0.0, 5e4, (n, 3))
    rate[3, 1] = np.nan
    powered = rng.random(n) > 0.3
    out = Outputs(times=np.arange(n, dtype=float), rate_dph=rate, bias_dph=rate, accel_g=rng.normal(0, 1, (n, 3)),
                  sensor_c=rng.normal(25, 10, n), probes_c={}, freq_hz=rng.normal(5e3, 1, (n, 3)),
                  valid=powered & (rng.random(n) > 0.5), powered=powered, trajectory=None)
    rows = SampleRows(out)
    for k in range(n):
        on = bool(out.powered[k])
        want = GyroSample(tuple(float(v) / 3600.0 for v in out.rate_dph[k]) if on else (0.0, 0.0, 0.0),
                          tuple(float(v) for v in out.accel_g[k]), float(out.sensor_c[k]),
                          tuple(float(v) for v in out.freq_hz[k]), bool(out.valid[k]))
        got = rows[k]
        assert pickle.dumps(got) == pickle.dumps(want)        # bit for bit (NaN included), same types

"""The chamber and table of a multi-gyro bench go through one ``DeviceTrack`` (``bench.sim.lookahead``):
advanced once per instant whichever unit is served first, every unit integrating from the same state
along the same inputs.  So each unit serves the bytes a bench of its own (same scenario, same
commands) serves, at 1000 Hz frames (instant by instant, frames between grid points) and at 1 Hz
(blocks ahead), commands included; and at 1 Hz every unit keeps its blocks as the first one does."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.sim.bench import SimulatedBench, lockstep_clock
from bench.sim.multibench import MultiGyroBench

SEED = 5


def _w1_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _drive(bench, units, instants: int, step_s: float):
    """Steps the bench's clock with the same commands at the same instants; per unit (source, psu
    model, w1 root): frames sent, probe temperatures and w1 files at every instant, lookahead stats."""
    clock = bench.clock
    bench.start()
    try:
        probes, files = [], []
        for i in range(instants):
            clock.sleep(step_s)
            if i == 2:
                for _, psu, _ in units:
                    psu.set_voltage(28.0)
                    psu.set_output(True)
            if i == instants // 3:
                bench.chamber_model.set_setpoint(35.0)
            if i == instants // 2:
                bench.table_model.interlock_close(1)
                bench.table_model.set_mode(1, "R")
                bench.table_model.set_rate_demand(1, 10.0)
            probes.append([src.probe_temperatures() for src, _, _ in units])
            files.append([_w1_files(root) for _, _, root in units])
        return probes, files, [dict(src.stats) for src, _, _ in units]
    finally:
        bench.stop()


def _multi(rate: int, instants: int, step_s: float, units: int = 3):
    bench = MultiGyroBench(units=units, clock=lockstep_clock(None, seed=SEED), seed=SEED, data_rate_hz=rate)
    probes, files, stats = _drive(bench, [(u.lookahead, u.psu_model, u.w1.root) for u in bench.units],
                                  instants, step_s)
    frames = [[(f.bench_time, f.frame) for f in u.gyro.sent_frames()] for u in bench.units]
    return frames, probes, files, stats, [u.scenario for u in bench.units]


def _single(scenario, rate: int, instants: int, step_s: float):
    bench = SimulatedBench(clock=lockstep_clock(None, seed=SEED), scenario=scenario, data_rate_hz=rate)
    probes, files, stats = _drive(bench, [(bench.lookahead, bench.psu_model, bench.w1_root)], instants, step_s)
    frames = [(f.bench_time, f.frame) for f in bench.gyro.sent_frames()]
    return frames, [p[0] for p in probes], [f[0] for f in files], stats[0]


@pytest.mark.parametrize("rate, instants, step_s", [(1000, 24, 0.25), (1, 90, 2.0)])
def test_every_unit_serves_the_bytes_of_a_bench_of_its_own(rate, instants, step_s):
    frames, probes, files, stats, scenarios = _multi(rate, instants, step_s)
    assert [len(f) for f in frames] == [instants * step_s * rate] * 3
    assert frames[0] != frames[1] != frames[2]                 # units differ (their own scenario draws)
    for k, scenario in enumerate(scenarios):
        own_frames, own_probes, own_files, own_stats = _single(scenario, rate, instants, step_s)
        assert frames[k] == own_frames, f"unit g{k + 1}: frames differ from a bench of its own"
        assert [p[k] for p in probes] == own_probes, f"unit g{k + 1}: probe temperatures differ"
        assert stats[k] == own_stats
        if k == 0:                                             # same probe serials: the same w1 files
            assert [f[0] for f in files] == own_files


def test_a_one_unit_multi_gyro_bench_is_the_single_bench():
    frames, probes, files, stats, scenarios = _multi(1, 40, 2.0, units=1)
    own_frames, own_probes, own_files, own_stats = _single(scenarios[0], 1, 40, 2.0)
    assert frames[0] == own_frames and [p[0] for p in probes] == own_probes
    assert [f[0] for f in files] == own_files and stats[0] == own_stats


def test_units_after_the_first_keep_their_blocks_ahead():
    """150 instants at 1 Hz: every unit computes as few blocks as the first (three commands each
    drop one), not one per instant."""
    _, _, _, stats, _ = _multi(1, 150, 1.0)
    first = stats[0]
    assert first["direct"] == 0 and first["blocks"] <= 25 and 3 <= first["dropped"] <= 6
    assert stats[1] == first and stats[2] == first

"""The chamber and table of a multi-gyro bench go through one ``DeviceTrack`` (``bench.sim.lookahead``):
advanced once per instant whichever unit is served first, every unit integrating from the same state
along the same inputs.  So each unit serves the bytes a bench of its own (same scenario, same
commands) serves, at 1000 Hz frames (instant by instant, frames between grid points) and at 1 Hz
(blocks ahead), commands included; and at 1 Hz every unit keeps its blocks as the first one does."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.sim.bench import SimulatedBench, lockstep_clock
from bench.sim.chamber_physics import ChamberModel
from bench.sim.lookahead import DeviceTrack, clone
from bench.sim.multibench import MultiGyroBench
from bench.sim.turntable import TableModel

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


def _config_pause(bench, gyro, source, psus, instants: int = 60):
    """1 Hz; the gyro's output stopped (``=CONFIG,1``) from instant 10 to 25 while the chamber's set
    point changes at 15: its source is then moved on by its probe conversions only."""
    clock = bench.clock
    bench.start()
    try:
        nodes = []
        for i in range(instants):
            clock.sleep(1.0)
            if i == 2:
                for psu in psus:
                    psu.set_voltage(28.0)
                    psu.set_output(True)
            if i in (10, 25):
                assert gyro.execute_command(f"=CONFIG,{int(i == 10)}") == f"CONFIG,{int(i == 10)}"
            if i == 15:
                bench.chamber_model.set_setpoint(35.0)
            nodes.append(source.node_temperatures())
        return [(f.bench_time, f.frame) for f in gyro.sent_frames()], nodes, dict(source.stats)
    finally:
        bench.stop()


def test_a_unit_whose_output_stops_while_the_chamber_changes_serves_its_own_bytes():
    multi = MultiGyroBench(units=3, clock=lockstep_clock(None, seed=SEED), seed=SEED, data_rate_hz=1)
    g2 = multi.units[1]
    frames, nodes, stats = _config_pause(multi, g2.gyro, g2.lookahead, [u.psu_model for u in multi.units])
    own = SimulatedBench(clock=lockstep_clock(None, seed=SEED), scenario=g2.scenario, data_rate_hz=1)
    own_frames, own_nodes, own_stats = _config_pause(own, own.gyro, own.lookahead, [own.psu_model])
    assert len(frames) == 45 and frames == own_frames
    assert nodes == own_nodes and stats == own_stats


class _Unit:                 # what the track reads of a unit: its last served instant
    def __init__(self, t: float) -> None:
        self._t = t


def test_a_unit_behind_integrates_on_each_instant_s_state_since():
    """A unit last served at 0 s asks at 3 s, after the models went through 1, 2 and 3 s with a set
    point command during 1 s and a table move during 2 s: its air, angles and rates come from the
    state at 0 s up to 1 s, from the commanded state at 1 s up to 2 s, from the one at 2 s beyond."""
    chamber, table = ChamberModel(air_c=23.0, setpoint_c=23.0), TableModel(axes=2)
    chamber.advance_to(0.0)
    table.advance_to(0.0)
    track = DeviceTrack(chamber, table, 0.0)
    behind, ahead = _Unit(0.0), _Unit(0.0)
    track.join(behind)
    track.join(ahead)
    at = {0.0: (clone(chamber), clone(table))}
    epochs = []
    for t in (1.0, 2.0, 3.0):
        if t == 2.0:
            chamber.set_setpoint(40.0)
        if t == 3.0:
            table.interlock_close(1)
            table.set_mode(1, "R")
            table.set_rate_demand(1, 10.0)
        at[t - 1.0] = (clone(chamber), clone(table))        # the state at the instant before, commands in
        epochs.append(track.instant(t))
        ahead._t = t
    assert epochs[1] == epochs[0] + 1 and epochs[2] == epochs[1] + 1     # each command seen once
    times = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0]
    air, angles, rates = track.states(0.0, times)
    want, base = [], None
    for g in times:                  # each instant's state advanced through the times of its stretch
        if base != min(2.0, float(int(g - 1e-9))):
            base = min(2.0, float(int(g - 1e-9)))
            c, tb = (clone(m) for m in at[base])
        c.advance_to(g)
        tb.advance_to(g)
        want.append((c.air_c, list(tb.angles()), list(tb.rates())))
    assert [(a, list(b), list(r)) for a, b, r in zip(air.tolist(), angles.tolist(), rates.tolist())] == want
    assert air[-1] > air[3] > air[0] and rates[-1][0] != 0.0 and rates[3][0] == 0.0
    behind._t = 3.0                                           # nobody behind: older states let go
    track.instant(4.0)
    assert list(track._kept) == [3.0]
    with pytest.raises(RuntimeError, match="no chamber and table state kept for bench instant 0.0"):
        track.states(0.0, [5.0])

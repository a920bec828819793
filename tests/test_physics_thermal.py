"""Thermal network of the simulated gyro: lag, probe disagreement, soak convergence, self-heating,
exact discretisation (step-size independence)."""
from __future__ import annotations

import numpy as np

from bench.sim.offline import chamber_air, simulate_full
from bench.sim.physics import GyroPhysics, PhysicsInputs, ThermalModel, orientation_matrix
from bench.sim.scenario import Scenario

PROBES = ("t1", "t2", "t3", "t4")


def _default() -> Scenario:
    return Scenario.builtin("default").with_changes(noise={})


def test_probes_lag_air_and_disagree_during_ramp_then_converge_at_soak():
    # unpowered so that a soaked gyro must end exactly at the air temperature
    prof = [("hold", 20.0, 600), ("ramp", 50.0, 1.0), ("hold", 50.0, 12 * 3600)]
    sim = simulate_full(_default(), prof, 1.0, powered_at_start=False, probe_resolution_c=None)
    ds = sim.dataset
    t = ds["time_s"]
    air = ds["chamber_pv"]
    probes = np.column_stack([ds[f"temp_{p}"] for p in PROBES])
    ramp_end = 600 + 30 * 60
    mid = (t > 600 + 15 * 60) & (t < ramp_end)
    # lag: every probe is colder than the air while heating
    assert np.all(probes[mid] < air[mid, None] - 0.5)
    # disagreement: the probes spread over more than 0.5 C during the ramp
    spread = probes.max(axis=1) - probes.min(axis=1)
    assert spread[mid].max() > 0.5
    # the probes reach the end temperature only after the air: lag of a few minutes at least
    reach_air = t[np.argmax(air > 49.0)]
    reach_probe = min(t[np.argmax(probes[:, i] > 49.0)] for i in range(4))
    assert reach_probe > reach_air + 300
    # soak: everything converges to the air (no self-heating when off)
    end = sim.outputs.trajectory.temps[-1]
    assert np.all(np.abs(end - 50.0) < 0.01)
    assert spread[-1] < 0.01


def test_self_heating_raises_internal_node_after_power_on():
    sc = _default()
    prof = [("power", "off"), ("hold", 25.0, 3600), ("power", "on"), ("hold", 25.0, 10 * 3600)]
    sim = simulate_full(sc, prof, 10.0, powered_at_start=False, probe_resolution_c=None)
    tr = sim.outputs.trajectory
    block = tr.temps[:, ThermalModel(sc.thermal).names.index("block")]
    t = sim.dataset["time_s"]
    before = block[t < 3600]
    after = block[t > 3600]
    assert np.allclose(before, 25.0, atol=1e-6)
    assert np.all(np.diff(after) > -1e-9)                 # monotonic rise towards the steady state
    expected = ThermalModel(sc.thermal).steady_state(25.0, True)
    assert abs(after[-1] - expected[-1]) < 0.05
    assert expected[-1] - 25.0 > 2.0                       # a visible self-heating rise
    # the internal node runs warmer than the probes on the case (heat flows outwards)
    probes = np.column_stack([sim.dataset[f"temp_{p}"] for p in PROBES])
    assert np.all(block[-1] > probes[-1, :3])
    # the gyro's internal temperature output is that node
    assert np.allclose(sim.outputs.sensor_c, block)


def test_exact_discretisation_is_step_size_independent():
    sc = _default()
    t_end = 4 * 3600.0

    def run(h: float) -> np.ndarray:
        def air(t: float) -> float:
            return 20.0 + 30.0 * min(max((t - 600.0) / 3600.0, 0.0), 1.0)    # 0.5 C/min ramp

        r = orientation_matrix("NUE")
        inputs = PhysicsInputs(air, lambda t: r, lambda t: (0.0, 0.0, 0.0), lambda t: True, lambda t: 0.0)
        phys = GyroPhysics(sc, 0.0, inputs, substep_s=h)
        out = phys.record(int(t_end / h), every=int(600 / h))
        return out.trajectory.temps

    fine = run(1.0)
    coarse = run(60.0)       # larger than every node time constant's fraction: must stay stable
    assert np.max(np.abs(fine - coarse)) < 0.01
    huge = run(600.0)        # one step per 10 min: still stable and close (inputs are piecewise linear)
    assert np.max(np.abs(fine - huge)) < 0.05


def test_node_rates_are_exact_derivatives():
    sim = simulate_full(_default(), [("hold", 10.0, 300), ("ramp", 40.0, 2.0), ("hold", 40.0, 3600)], 1.0,
                        probe_resolution_c=None)
    tr = sim.outputs.trajectory
    numeric = np.gradient(tr.temps, tr.times, axis=0) * 60.0
    assert np.max(np.abs(numeric[5:-5] - tr.rates[5:-5])) < 0.01     # C/min


def test_live_probe_temperatures_follow_advance():
    sc = _default()
    r = orientation_matrix("NUE")
    inputs = PhysicsInputs(lambda t: 20.0 if t < 100 else 40.0, lambda t: r, lambda t: (0.0, 0.0, 0.0),
                           lambda t: False, lambda t: None)
    phys = GyroPhysics(sc, 0.0, inputs)
    phys.advance_to(50.0)
    assert all(abs(v - 20.0) < 1e-9 for v in phys.probe_temperatures().values())
    phys.advance_to(3 * 3600.5)
    temps = phys.probe_temperatures()
    assert set(temps) == set(PROBES)
    assert all(20.0 < v < 40.0 for v in temps.values())
    phys.advance_to(40 * 3600.0)
    assert all(abs(v - 40.0) < 0.01 for v in phys.probe_temperatures().values())


def test_chamber_air_is_rate_limited():
    sp = np.concatenate([np.full(10, 20.0), np.full(2000, 60.0)])
    air = chamber_air(sp, 1.0, 20.0, 60.0, 5.0)
    assert np.max(np.diff(air)) <= 5.0 / 60.0 + 1e-12
    assert abs(air[-1] - 60.0) < 0.01

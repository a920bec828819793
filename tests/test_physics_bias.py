"""Gyro output model: declared bias terms, Earth-rate projection, effects, live == offline, HRG."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench.sim.offline import simulate_full
from bench.sim.physics import GyroPhysics, PhysicsInputs
from bench.sim.scenario import Scenario
from tests import REFERENCE_DIR

# independent constants (not imported from the code under test).  bench.fit.base.EARTH_RATE_DPH is
# 15.041067 (rounded; 15.0410686 from 7.2921158553e-5 rad/s): comparisons involving the Earth rate use
# atol 1e-5 deg/h.
OMEGA_DPH = 7.2921158553e-5 * 180.0 / math.pi * 3600.0
EARTH_TOL = 1e-5
UNIT = {"E": (1, 0, 0), "W": (-1, 0, 0), "N": (0, 1, 0), "S": (0, -1, 0), "U": (0, 0, 1), "D": (0, 0, -1)}
EIGHT = ("ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")   # seed 000 section 3.2 (+ NUE)


def earth_body(code: str, lat_deg: float) -> np.ndarray:
    r = np.array([UNIT[c] for c in code], dtype=float).T          # columns = body axes in ENU
    lat = math.radians(lat_deg)
    return r.T @ (OMEGA_DPH * np.array([0.0, math.cos(lat), math.sin(lat)]))


def quiet(name: str = "default", **changes) -> Scenario:
    """A built-in scenario without gyro noise, with the given top-level fields replaced."""
    sc = Scenario.builtin(name)
    return sc.with_changes(noise={}, accel_noise_g=0.0, **changes)


def test_bias_equals_declared_function():
    terms = {"t1": 0.01, "t1^2": 1e-4, "dt1": 0.02, "(t1-t3)": 0.05, "t1*dt1": 0.003, "d(t2-t4)": 0.1,
             "block^3": 1e-6}
    sc = quiet(bias={"x": {"intercept_dph": 0.1, "t0_c": 20.0, "terms": terms}})
    prof = [("hold", 10.0, 1200), ("ramp", 45.0, 1.5), ("hold", 45.0, 1800), ("ramp", 0.0, 0.8)]
    sim = simulate_full(sc, prof, 1.0, "NUE", probe_resolution_c=None)
    ds, tr = sim.dataset, sim.outputs.trajectory
    names = ["t1", "t2", "t3", "t4", "block"]
    temp = {n: tr.temps[:, i] for i, n in enumerate(names)}
    rate = {n: np.gradient(temp[n], tr.times) * 60.0 for n in names}     # C/min, numerical
    assert np.allclose(temp["t1"], ds["temp_t1"])
    c = {n: temp[n] - 20.0 for n in names}
    expected = (0.1 + 0.01 * c["t1"] + 1e-4 * c["t1"] ** 2 + 0.02 * rate["t1"] + 0.05 * (temp["t1"] - temp["t3"])
                + 0.003 * c["t1"] * rate["t1"] + 0.1 * (rate["t2"] - rate["t4"]) + 1e-6 * c["block"] ** 3)
    got = ds["gyro_x"] - earth_body("NUE", sc.latitude_deg)[0]
    sl = slice(3, -3)           # np.gradient is one-sided at the ends
    assert np.max(np.abs(got[sl] - expected[sl])) < 2e-4
    # channels without declared terms carry only the Earth rate
    assert np.allclose(ds["gyro_y"], earth_body("NUE", sc.latitude_deg)[1], rtol=0, atol=EARTH_TOL)
    assert abs(np.ptp(expected)) > 0.3          # the test exercises a real variation


@pytest.mark.parametrize("code", EIGHT + ("NUE",))
def test_earth_rate_projection_for_orientation_codes(code):
    sc = quiet(bias={})
    ds = simulate_full(sc, [("hold", 25.0, 20)], 1.0, code).dataset
    want = earth_body(code, sc.latitude_deg)
    got = np.array([ds[f"gyro_{ch}"][-1] for ch in "xyz"])
    assert np.allclose(got, want, rtol=0, atol=EARTH_TOL)
    assert set(ds["orientation"]) == {code}


def test_scale_factor_and_installation_matrix_act_on_input_rate():
    m = [[1.0, 2e-3, 0.0], [0.0, 1.0, -1e-3], [5e-4, 0.0, 1.0]]
    effects = {"installation": {"matrix": m},
               "scale_factor_temperature": {"ppm": {"x": 1000.0}, "ppm_per_c": {"x": 100.0}}}
    sc = quiet(bias={}, effects=effects)
    sim = simulate_full(sc, [("hold", 45.0, 20 * 3600)], 60.0, "NUE", powered_at_start=False,
                        probe_resolution_c=None)
    w = np.array(m) @ earth_body("NUE", sc.latitude_deg)
    t_own = sim.outputs.trajectory.temps[-1, 0]         # x's own node is t1
    sf = 1e-6 * (1000.0 + 100.0 * (t_own - 25.0))
    got = [sim.outputs.rate_dph[-1, i] for i in range(3)]
    assert got[0] == pytest.approx((1 + sf) * w[0], abs=EARTH_TOL)
    assert got[1] == pytest.approx(w[1], abs=EARTH_TOL) and got[2] == pytest.approx(w[2], abs=EARTH_TOL)
    assert abs(got[0] - w[0]) > 0.02            # the scale-factor error is visible (~3000 ppm of 10 deg/h)


def test_warmup_decays_exponentially_after_power_on():
    sc = quiet(bias={}, effects={"warmup": {"tau_s": 600.0, "amplitude_dph": {"x": 0.5}}}, startup_invalid_s=2.0)
    prof = [("power", "off"), ("hold", 25.0, 600), ("power", "on"), ("hold", 25.0, 3600)]
    ds = simulate_full(sc, prof, 1.0, "ENU").dataset
    t = ds["time_s"]
    assert np.all(np.isnan(ds["gyro_x"][t < 602]))        # off, then status invalid for 2 s
    ok = t >= 602
    expected = 0.5 * np.exp(-(t[ok] - 600.0) / 600.0)       # body x = East: no Earth rate
    assert np.allclose(ds["gyro_x"][ok], expected, atol=1e-12)


def test_g_sensitivity_follows_gravity_projection():
    sc = quiet(bias={}, effects={"g_sensitivity": {"dph_per_g": {"x": [0.0, 0.0, 0.02]}}})
    prof = [("hold", 25.0, 100), ("orient", "ESD"), ("wait", 100)]
    ds = simulate_full(sc, prof, 1.0, "ENU").dataset
    up = ds["gyro_x"][ds["orientation"] == "ENU"]
    down = ds["gyro_x"][ds["orientation"] == "ESD"]
    assert np.allclose(up, 0.02, atol=1e-12) and np.allclose(down, -0.02, atol=1e-12)


def test_hysteresis_branches_and_memory():
    amp = 0.03
    sc = quiet(bias={}, effects={"hysteresis": {"driver": "t1", "width_c": 1.5, "amplitude_dph": {"x": amp}}})
    prof = [("hold", 25.0, 3600), ("ramp", 45.0, 1.0), ("hold", 45.0, 6 * 3600), ("ramp", 25.0, 1.0),
            ("hold", 25.0, 6 * 3600), ("ramp", 5.0, 1.0), ("hold", 5.0, 6 * 3600), ("ramp", 25.0, 1.0),
            ("hold", 25.0, 6 * 3600)]
    sim = simulate_full(sc, prof, 10.0, "ENU", probe_resolution_c=None)
    ds = sim.dataset
    t = ds["time_s"]
    after_cooling = ds["gyro_x"][np.searchsorted(t, 3600 + 1200 + 6 * 3600 + 1200 + 6 * 3600 - 10)]
    after_heating = ds["gyro_x"][-1]
    assert after_cooling == pytest.approx(-amp, abs=1e-3)
    assert after_heating == pytest.approx(amp, abs=1e-3)
    # memory: during the last soak the state does not relax towards zero
    last_soak = ds["gyro_x"][t > t[-1] - 3 * 3600]
    assert np.ptp(last_soak) < 1e-4 and abs(last_soak.mean() - amp) < 1e-3


def test_thermal_lag_drives_bias_by_lagged_temperature():
    tau = 900.0
    sc = quiet(bias={"x": {"terms": {"t1": 0.1}}}, effects={"thermal_lag": {"tau_s": tau}})
    prof = [("hold", 20.0, 1800), ("ramp", 50.0, 0.5), ("hold", 50.0, 4 * 3600)]
    sim = simulate_full(sc, prof, 1.0, "ENU", probe_resolution_c=None)
    t1 = sim.outputs.trajectory.temps[:, 0]
    lag = np.empty_like(t1)                      # independent explicit Euler at 0.1 s
    y = t1[0]
    for k in range(t1.size):
        prev = t1[k - 1] if k else t1[0]
        for j in range(10):
            u = prev + (t1[k] - prev) * (j + 0.5) / 10
            y += 0.1 * (u - y) / tau
        lag[k] = y
    got = sim.dataset["gyro_x"]
    assert np.max(np.abs(got - 0.1 * (lag - 25.0))) < 2e-4
    # and it differs visibly from the unlagged function during the ramp
    assert np.max(np.abs(got - 0.1 * (t1 - 25.0))) > 0.05


def test_time_drift_sinusoid_and_cross_channel_temperature():
    effects = {"time_drift": {"dph_per_h": {"x": 0.01}},
               "unexplained": {"sinusoids": [{"channel": "y", "amplitude_dph": 0.05, "period_s": 3600.0}]},
               "cross_channel_temperature": {"z": {"source_channel": "x", "dph_per_c": 0.02}}}
    sc = quiet(bias={}, effects=effects)
    sim = simulate_full(sc, [("hold", 25.0, 600), ("ramp", 35.0, 1.0), ("hold", 35.0, 7200)], 1.0, "ENU",
                        probe_resolution_c=None)
    ds, tr = sim.dataset, sim.outputs.trajectory
    t = ds["time_s"]
    earth = earth_body("ENU", sc.latitude_deg)
    assert np.allclose(ds["gyro_x"] - earth[0], 0.01 * t / 3600.0, rtol=0, atol=EARTH_TOL)
    assert np.allclose(ds["gyro_y"] - earth[1], 0.05 * np.sin(2 * np.pi * t / 3600.0), rtol=0, atol=EARTH_TOL)
    assert np.allclose(ds["gyro_z"] - earth[2], 0.02 * (tr.temps[:, 0] - 25.0), rtol=0, atol=EARTH_TOL)


def test_random_steps_are_piecewise_constant_and_seeded():
    effects = {"unexplained": {"random_steps": {"channels": ["x"], "rate_per_h": 2.0, "sigma_dph": 0.05}}}
    sc = quiet(bias={}, effects=effects)
    a = simulate_full(sc, [("hold", 25.0, 10 * 3600)], 10.0, "ENU").dataset["gyro_x"]
    b = simulate_full(sc, [("hold", 25.0, 10 * 3600)], 10.0, "ENU").dataset["gyro_x"]
    c = simulate_full(sc, [("hold", 25.0, 10 * 3600)], 10.0, "ENU", seed=99).dataset["gyro_x"]
    jumps = np.count_nonzero(np.abs(np.diff(a)) > 1e-12)
    assert 5 <= jumps <= 45                      # ~20 expected in 10 h
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_live_sampling_equals_offline_record():
    sc = Scenario.builtin("fog_effects")         # every effect and all noise on
    prof = [("hold", 20.0, 900), ("ramp", 35.0, 2.0), ("hold", 35.0, 900)]
    off = simulate_full(sc, prof, 1.0, "NUE", probe_resolution_c=None)
    n = len(off.dataset)
    inputs = off.physics.inputs
    live = GyroPhysics(sc, 0.0, PhysicsInputs(inputs.air_temp_c, inputs.body_to_level, inputs.table_rate_body_dps,
                                              inputs.powered, inputs.power_on_time), output_period_s=1.0)
    half = n // 2
    first = [live.sample(float(k)) for k in range(1, half + 1)]
    rest = live.sample_many(np.arange(half + 1, n + 1, dtype=float))
    got = np.array([s.rate_dps for s in first + rest]) * 3600.0
    want = np.column_stack([off.dataset[f"gyro_{c}"] for c in "xyz"])
    ok = ~np.isnan(want[:, 0])
    assert np.allclose(got[ok], want[ok], rtol=0, atol=1e-9)
    temps = live.probe_temperatures()
    assert temps["t2"] == pytest.approx(off.dataset["temp_t2"][-1], abs=1e-9)
    # a sample between grid points lies between its neighbours' thermal states (exact sub-step)
    s = live.sample(n + 0.5)
    assert s.valid and len(s.rate_dps) == 3 and s.freq_hz is None


def test_hrg_frequency_reproduces_seed002_table1_at_soak():
    table = np.genfromtxt(REFERENCE_DIR / "hrg_frequency_temperature.csv", delimiter=",", names=True,
                          skip_header=3)
    sc = Scenario.builtin("hrg").with_changes(noise={})
    for chamber in (-40.0, 0.0, 50.0):
        sim = simulate_full(sc, [("hold", chamber, 30 * 3600)], 600.0, "NUE", probe_resolution_c=None)
        ds = sim.dataset
        for ch, probe in zip("xyz", ("t1", "t2", "t3")):
            case = ds[f"temp_{probe}"][-1]
            heat = case - chamber
            assert 3.0 < heat < 7.0                        # Table 1: cases 3.6-6.3 C above the chamber
            cubic = np.polyfit(table[f"ds18b20_g{ch}_c"], table[f"freq_g{ch}_hz"], 3)   # residual std < 0.01 Hz
            table_freq = np.polyval(cubic, case)
            assert ds[f"freq_{ch}"][-1] == pytest.approx(table_freq, abs=0.05)

"""Noise of the simulated gyro: ARW by Allan deviation, Gauss-Markov, rate random walk, seeds."""
from __future__ import annotations

import allantools
import numpy as np
import pytest

from bench.sim.offline import simulate
from bench.sim.physics import GyroPhysics, PhysicsInputs, orientation_matrix
from bench.sim.scenario import Scenario

R_ENU = orientation_matrix("ENU")


def _scenario(noise: dict) -> Scenario:
    return Scenario.builtin("default").with_changes(bias={}, noise=noise, accel_noise_g=0.0)


def _static_inputs() -> PhysicsInputs:
    return PhysicsInputs(lambda t: 25.0, lambda t: R_ENU, lambda t: (0.0, 0.0, 0.0), lambda t: True,
                         lambda t: -1e9)


def test_white_noise_allan_deviation_matches_arw():
    arw = 0.003                                      # deg/sqrt(h)
    sc = _scenario({"x": {"arw_deg_rt_h": arw}})
    ds = simulate(sc, [("hold", 25.0, 30000)], 1.0, "ENU")      # body x East: no Earth rate
    x = ds["gyro_x"]
    taus, adev, _, _ = allantools.oadev(x, rate=1.0, data_type="freq", taus=np.array([1.0, 10.0, 100.0]))
    assert adev[0] == pytest.approx(60.0 * arw, rel=0.10)       # N / sqrt(tau) with tau in hours, deg/h
    assert adev[2] == pytest.approx(60.0 * arw / 10.0, rel=0.25)
    assert np.all(ds["gyro_y"] - ds["gyro_y"][0] == 0.0)          # no noise declared on y


def test_white_noise_scales_with_output_period():
    arw = 0.01
    sc = _scenario({"z": {"arw_deg_rt_h": arw}})
    phys = GyroPhysics(sc, 0.0, _static_inputs(), output_period_s=0.001)
    z = np.array([s.rate_dps[2] for s in phys.sample_many(np.arange(1, 20001) * 0.001)]) * 3600.0
    z -= z.mean()
    assert z.std() == pytest.approx(60.0 * arw / np.sqrt(0.001), rel=0.05)


def test_gauss_markov_and_rate_random_walk_levels():
    sc = _scenario({"x": {"gauss_markov": [{"sigma_dph": 0.01, "tau_s": 60.0}]},
                    "y": {"rrw_dph_rt_h": 0.02}})
    phys = GyroPhysics(sc, 0.0, _static_inputs(), substep_s=60.0)      # exact AR(1) / walk steps
    out = phys.record(400 * 60)
    gm = out.bias_dph[:, 0]
    assert gm.std() == pytest.approx(0.01, rel=0.1)
    lag1 = np.corrcoef(gm[:-1], gm[1:])[0, 1]                       # 60 s spacing: exp(-1)
    assert lag1 == pytest.approx(np.exp(-1.0), abs=0.05)
    walk = out.bias_dph[::60, 1]                                     # hourly values
    assert np.diff(walk).std() == pytest.approx(0.02, rel=0.15)      # K * sqrt(1 h)


def test_noise_is_seeded_and_independent_of_chunking():
    sc = Scenario.builtin("fog_effects")
    prof = [("hold", 25.0, 2000)]
    a = simulate(sc, prof, 1.0, "NUE")
    b = simulate(sc, prof, 1.0, "NUE")
    c = simulate(sc, prof, 1.0, "NUE", seed=1234)
    for ch in "xyz":
        assert np.array_equal(a[f"gyro_{ch}"], b[f"gyro_{ch}"], equal_nan=True)
        assert not np.allclose(a[f"gyro_{ch}"][10:], c[f"gyro_{ch}"][10:])
    # one record of 2000 steps == two records of 1000 steps (same streams, same states)
    p1 = GyroPhysics(sc, 0.0, _static_inputs())
    p2 = GyroPhysics(sc, 0.0, _static_inputs())
    whole = p1.record(2000).rate_dph
    halves = np.vstack([p2.record(1000).rate_dph, p2.record(1000).rate_dph])
    assert np.allclose(whole, halves, rtol=0, atol=1e-12)

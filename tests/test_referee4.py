"""The fourth close-the-loop referee: checks of its generator, and three cases scored through the CLI.

The full measurement is ``python -m tests.referee4.score --seeds 5 --first-seed 1``.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from bench.fit.closeloop_search import AMBIGUOUS_DBIC
from bench.fit.csvio import parse_csv_text
from tests.referee4.cases import build_case
from tests.referee4.effects import lag_irregular, play_operator, reversal_trigger
from tests.referee4.oracle import channel_score
from tests.referee4.physics import (NoiseSpec, allan_deviation, flicker_noise, gyro_noise,
                                    quantise_output)
from tests.referee4.score import score_case


def test_white_noise_gives_its_angle_random_walk():
    spec = NoiseSpec(arw_dps_rth=0.005, bias_inst_dph=0.0, rrw_dph_rth=0.0, quant_arcsec=0.0)
    y = gyro_noise(200_000, 1.0, spec, np.random.default_rng(1))
    adev = allan_deviation(y, 1.0, [1.0, 100.0])
    assert adev[0] == pytest.approx(0.005 * 60.0, rel=0.02)          # N / sqrt(tau in h) at 1 s
    assert adev[1] == pytest.approx(0.005 * 6.0, rel=0.08)           # and at 100 s


def test_flicker_noise_sits_at_0664_b():
    b = 0.004
    y = flicker_noise(400_000, 1.0, b, np.random.default_rng(2))
    adev = allan_deviation(y, 1.0, [30.0, 100.0, 300.0])
    assert np.all(np.abs(adev / (0.664 * b) - 1) < 0.15), adev / (0.664 * b)


def test_rate_random_walk_grows_as_k_sqrt_tau_over_3():
    k = 0.002                                                        # deg/h/sqrt(h)
    spec = NoiseSpec(arw_dps_rth=0.0, bias_inst_dph=0.0, rrw_dph_rth=k, quant_arcsec=0.0)
    vals = [allan_deviation(gyro_noise(100_000, 1.0, spec, np.random.default_rng(s)), 1.0, [1000.0])[0]
            for s in range(4)]
    assert np.mean(vals) == pytest.approx(k / 60.0 * np.sqrt(1000.0 / 3.0), rel=0.25)


def test_angle_quantisation_never_accumulates():
    rate = np.full(10_000, 3.7)                                      # deg/h
    out = quantise_output(rate, 1.0, 1.0, np.random.default_rng(3))
    assert len(np.unique(out)) > 1                                  # it is quantised per sample...
    assert abs(out.mean() - 3.7) * 10_000 / 3600 < 1.0 / 3600 + 1e-12  # ...but the angle is exact to Q


def test_memory_operators():
    x = np.concatenate([np.linspace(0, 10, 101), np.linspace(10, 0, 101)])
    play = play_operator(x, 2.0)
    assert play[50] == pytest.approx(-1.0) and play[-1] == pytest.approx(1.0)
    rev = reversal_trigger(x, 1.0)
    assert rev[50] == 1.0 and rev[-1] == -1.0 and rev[101 + 5] == 1.0   # flips only after 1 C back
    t = np.arange(0.0, 5000.0)
    lagged = lag_irregular(t, np.where(t > 100, 1.0, 0.0), 600.0)
    assert lagged[700] == pytest.approx(1 - np.exp(-599.5 / 600.0), rel=0.01)


def test_seeding_is_deterministic():
    a, b = build_case("lag_other_probe", 3), build_case("lag_other_probe", 3)
    assert a.texts == b.texts and a.truth == b.truth
    c = build_case("lag_other_probe", 4)
    assert c.texts["train"] != a.texts["train"]


@pytest.mark.parametrize("cls,seed", [("two_effects", 2), ("complete_gradient_flicker", 1)])
def test_csv_reads_back_through_the_product_reader(cls, seed):
    case = build_case(cls, seed)
    for run in ("train", "validate"):
        ds = parse_csv_text(case.texts[run], source=run)
        cols = case.columns[run]
        assert ds.meta["channel_probes"] == {"x": "t1", "y": "t2", "z": "t3"}
        for name, ours in cols.items():
            theirs = np.asarray(ds.columns[name], dtype=float)
            assert np.array_equal(np.isnan(theirs), np.isnan(ours)), name
            ok = ~np.isnan(ours)
            assert np.allclose(theirs[ok], ours[ok], atol=1e-4 if name.startswith("gyro_") else 0.06), name


def test_oracle_reaches_the_noise_and_the_declared_model_does_not():
    case = build_case("gradient_pair", 2)
    for ch, tr in case.truth.items():
        s = channel_score(case, ch)
        assert s.oracle_std100 < 1.5 * case.noise_std100_dph, (ch, s, case.noise_std100_dph)
        if tr["effects"]:
            assert s.before_std100 > 3 * s.oracle_std100, (ch, s)


# scored through `bench close-loop` (its JSON only); seeds from the first scoring round
SCORED = [
    pytest.param("temp_rate_cross", 1, id="temp_rate_cross-1"),
    pytest.param("time_drift", 1, id="time_drift-1"),
    pytest.param("lag_other_probe", 1, id="lag_other_probe-1", marks=pytest.mark.xfail(
        strict=True, reason="y's lag of t1 is named on its own probe t2: the training run puts lag(t2) "
                            "4.6 ahead in BIC (named in ambiguous_with); after 1.37x the oracle, "
                            "explained; z's lag of t1 is found (measured)")),
    # z: a relay of t3 chosen on TRAIN took the in-range validation error from 0.760 to 0.208 deg/h
    # (the oracle's 0.232), but its skill z was 1.23 and nothing was added: the noise model fitted to
    # the validation residual with the relay carried a random-walk term over the run that claimed far
    # more variance than that residual holds; its level is bounded by the residual now
    pytest.param("hysteresis_relay_rate", 105, id="hysteresis_relay_rate-105"),
]


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    """``score_case`` run once per case for this module: (result, the product's report JSON)."""
    keep, done = tmp_path_factory.mktemp("referee4"), {}

    def run(cls: str, seed: int) -> tuple[dict, dict]:
        if (cls, seed) not in done:
            result = score_case(cls, seed, keep=keep)
            done[cls, seed] = (result, json.loads((keep / f"{cls}-{seed}.json").read_text()))
        return done[cls, seed]
    return run


@pytest.mark.parametrize("cls,seed", SCORED)
def test_scored_case(cls, seed, scored):
    r, _ = scored(cls, seed)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures


def test_a_lag_of_another_probe_is_found_on_that_probe():
    # y's bias follows t4 through a lag; y's own probe is t2.  Before the lag's absolute form
    # (lag of T4 itself, not lag - T4) it came out as lag(t4) plus a gradient(t1, t4) (measured)
    r = score_case("lag_other_probe", 13)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures


def test_a_lag_the_training_run_cannot_place_names_the_other_probe(scored):
    # y's bias follows t1 through a lag (tau 1963 s); y's own probe is t2, a node that follows t1.  On
    # the training run lag(t2) is 4.6 ahead of lag(t1) in BIC (blocked CV alike): below the ambiguity
    # bar, so the report must name the true probe beside the one it chose.  Ranking the two by their GLS
    # likelihood under the noise model, or on 10-s means, was measured and not kept (wrong on more of the
    # fifth referee's lags than it mended)
    _, report = scored("lag_other_probe", 1)
    (lag,) = report["channels"]["y"]["effects_added"]
    assert lag["kind"] == "thermal_lag", lag
    alike = [a for a in lag["ambiguous_with"] if a["kind"] == "thermal_lag"]
    assert any(a["params"]["probe"] == "t1" and a["bic_margin"] < AMBIGUOUS_DBIC for a in alike), lag["ambiguous_with"]


def test_a_rate_relay_is_found_whatever_rate_filter_the_element_has():
    # the relay switches on a 120-s rate; with the product's one 300-s rate filter it was named on t2
    # instead of t1 and left 6.5x the oracle's error (measured); the filter window is now a variant
    r = score_case("hysteresis_relay_rate", 13)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures


@pytest.mark.parametrize("cls,seed", [("unrecorded_heater", 14), ("unrecorded_humidity", 12)])
def test_effects_that_fit_a_share_of_an_unrecorded_driver_are_not_its_cause(cls, seed, tmp_path):
    # before: gradient(t1,t4) (heater 14, 10 % of the excess removed) and two hysteresis memories
    # (humidity 12, 11 %) were added, verdict partly_explained
    r = score_case(cls, seed, keep=tmp_path)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures
    report = json.loads((tmp_path / f"{cls}-{seed}.json").read_text())
    left_out = [e for ch in report["channels"].values() for e in ch["effects_not_generalised"]
                if e["status"].startswith("not the cause")]
    assert left_out and all(e["share_of_excess_variance"] < 0.5 for e in left_out), left_out


def test_a_rate_beside_a_logger_outage_is_the_slope_of_the_readings_present():
    # y's bias follows dT4/dt; the validation run has three logger outages (153-291 s).  With the rate
    # set to zero where its window reached into an outage, the right effect left 1.90x the oracle's
    # error and the verdict partly_explained (measured); the oracle computes the rate there too
    r = score_case("rate_probe", 15)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures


def test_an_effect_whose_size_changes_between_the_runs_is_not_the_cause_of_an_unrecorded_driver(tmp_path):
    # y's bias follows a heater no column records.  A Duhem memory of t4 fitted a share of it on the
    # training run and removed 70 % of the validation variance above the noise (over the share rule's
    # bar: partly_explained, measured); the validation run holds it at 1.34x its training size
    r = score_case("unrecorded_heater", 15, keep=tmp_path)
    failures = {c["channel"]: c["failures"] for c in r["channels"] if c["failures"]}
    assert r["ok"], failures
    y = json.loads((tmp_path / "unrecorded_heater-15.json").read_text())["channels"]["y"]
    left_out = [e for e in y["effects_not_generalised"] if e["status"].startswith("not the cause")]
    assert left_out and all(e["share_of_excess_variance"] >= 0.5 for e in left_out), left_out
    assert any(abs(np.log(e.get("validation_scale", 1.0))) > np.log(1.25) for e in left_out), left_out

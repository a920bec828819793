"""The referee corpus itself: its physics and its oracle behave as documented (these do not depend
on the product's close-the-loop)."""
from __future__ import annotations

import numpy as np
import pytest

from tests.corpus import physics as ph
from tests.corpus.cases import make_case
from tests.corpus.referee import reference


def test_network_starts_in_equilibrium_and_follows_a_soak():
    net = ph.random_network(np.random.default_rng(3))
    net["room_c"] = 30.0
    nodes = ph.network_temperatures(np.full(40000, 30.0), net)
    for name, t in nodes.items():
        assert abs(t[0] - 30.0) < 1e-9 and abs(t[-1] - 30.0) < 1e-9, name
    net = ph.random_network(np.random.default_rng(4))
    net["room_c"] = 10.0
    step = np.concatenate([np.full(100, 0.0), np.full(60000, 10.0)])
    nodes = ph.network_temperatures(step, net)
    assert all(abs(t[-1] - 10.0) < 0.01 for t in nodes.values())
    assert nodes["case"][1000] > nodes["coil_x"][1000] - 5.0      # heat flows inwards from the case
    # at a cold soak the base plate sits between the air and the room (heat leaks in through the shaft)
    net["room_c"] = 25.0
    nodes = ph.network_temperatures(np.full(20000, -30.0), net)
    assert -30.0 < nodes["base"][-1] < 25.0 and nodes["base"][-1] > nodes["coil_x"][-1]


def test_probes_are_ds18b20_quantised():
    rng = np.random.default_rng(1)
    x = ph.read_probe(np.linspace(0, 10, 5000), 2.0, 0.1, 0.01, rng)
    assert np.allclose(x / ph.QUANTUM_C, np.round(x / ph.QUANTUM_C))


@pytest.mark.parametrize("arw,bi", [(0.005, 0.0), (0.001, 0.01)])
def test_gyro_noise_has_the_ieee_allan_levels(arw, bi):
    import allantools

    x = ph.gyro_noise(400_000, np.random.default_rng(7), arw, bi, 0.0)
    _, adev, _, _ = allantools.oadev(x, rate=1.0, data_type="freq", taus=np.array([1.0, 1000.0]))
    if bi == 0:
        assert abs(adev[0] / (arw * 60.0) - 1) < 0.05
    else:
        assert abs(adev[1] / (0.664 * bi) - 1) < 0.35        # flicker floor, one realisation


def test_the_output_filter_correlates_neighbouring_samples_and_keeps_the_100_s_level():
    raw = ph.gyro_noise(200_000, np.random.default_rng(3), 0.005, 0.0, 0.0)
    filtered = ph.gyro_noise(200_000, np.random.default_rng(3), 0.005, 0.0, 0.0, filter_s=4.0)
    assert np.corrcoef(filtered[:-1], filtered[1:])[0, 1] == pytest.approx(np.exp(-1 / 4.0), abs=0.02)
    std100 = [np.std(x.reshape(-1, 100).mean(axis=1)) for x in (raw, filtered)]
    assert std100[1] == pytest.approx(std100[0], rel=0.06)


def test_oracle_reaches_the_noise_floor_and_complete_models_need_nothing():
    case = make_case("effect_off_own_probe_gradient", 1)
    ch = next(iter(case.truth))
    ref = reference(case, ch)
    assert ref.before_in > 3 * ref.oracle_in
    assert ref.oracle_in < 1.3 * case.floors[ch]
    case = make_case("complete_validation_colder", 1)
    ch = next(iter(case.truth))
    ref = reference(case, ch)
    assert ref.coverage < 0.95
    assert ref.before_in == pytest.approx(ref.oracle_in)


def test_cases_are_reproducible_per_seed():
    a, b = make_case("two_effects", 3), make_case("two_effects", 3)
    for col in a.train.columns:
        assert np.array_equal(np.asarray(a.train[col]), np.asarray(b.train[col]), equal_nan=col != "orientation")
    assert a.truth.keys() == b.truth.keys()


def test_a_lag_that_imitates_a_gradient_at_a_time_constant_between_grid_points_is_a_look_alike():
    # the gradient t1-t2 of this unit is imitated by a lag of t1 within 0.02 noise floors at 19.5 min,
    # not at 10, 30 or 90 min (0.87-1.24 floors): the look-alike search must try time constants finely
    truth = make_case("effect_validation_colder", 1).truth["y"]
    (gradient,) = truth.effects
    assert (gradient.kind, set(gradient.probes)) == ("gradient", {"t1", "t2"})
    (looks,) = truth.lookalikes
    assert ["thermal_lag", ["t1"]] in [[k, list(p)] for k, p in looks]


def _report(effects, verdict, residual):
    return {"effects_added": [{"kind": k, "params": p} for k, p in effects], "verdict": verdict,
            "_residuals": {"after": (None, residual)}}


def test_referee_passes_the_truth_and_names_each_failure():
    from tests.corpus.referee import score_channel

    case = make_case("two_effects", 2)
    ch = next(iter(case.truth))
    ref = reference(case, ch)
    truth = case.truth[ch]
    right = [(e.kind, {"probe": e.probes[0]} if len(e.probes) == 1 else
              {"probes": "-".join(e.probes)} if e.probes else {}) for e in truth.effects]
    ok = score_channel(case, ch, _report(right, "explained", ref.residual_oracle))
    assert ok.passed, ok.reasons
    wrong_kind = score_channel(case, ch, _report(right[:1], "explained", ref.residual_oracle))
    assert [r.split(":")[0] for r in wrong_kind.reasons] == ["kinds"]
    dishonest = score_channel(case, ch, _report(right, "no_effect_missing", ref.residual_oracle))
    assert [r.split(":")[0] for r in dishonest.reasons] == ["verdict"]
    nothing_gained = score_channel(case, ch, _report(right, "explained", ref.residual_before))
    assert [r.split(":")[0] for r in nothing_gained.reasons] == ["error"]
    worse = score_channel(case, ch, _report(right, "explained", 2 * ref.residual_before))
    assert {r.split(":")[0] for r in worse.reasons} == {"worse", "error"}


def test_written_case_reads_back_as_measured_data(tmp_path):
    import json

    from bench.fit.csvio import read_csv
    from tests.corpus.cases import write_case

    case = make_case("effect_off_own_probe_g_sensitivity", 1)
    record = write_case(case, tmp_path)
    back = read_csv(tmp_path / "train.csv")
    coils = {node[-1]: probe for probe, node in case.probe_nodes.items() if node.startswith("coil_")}
    assert back.meta["channel_probes"] == {"x": coils["x"], "y": coils["y"], "z": coils["z"]}
    assert "latitude_deg" in back.meta
    assert np.array_equal(back["temp_t2"], case.train["temp_t2"])
    assert list(back["orientation"]) == list(case.train["orientation"])
    assert json.loads((tmp_path / "truth.json").read_text())["channels"] == json.loads(json.dumps(record["channels"]))


def test_block_means_of_a_column_do_not_depend_on_the_columns_beside_it():
    # the look-alike search fits block means assembled from parts; a design's must be its columns', bit for bit
    from tests.corpus.generator import block_means100

    rng = np.random.default_rng(5)
    cols = [np.ones(7200), *(rng.normal(size=7200) * 10.0 ** k for k in range(4))]
    whole = block_means100(cols)
    parts = np.column_stack([block_means100(cols[:2]), block_means100(cols[2:4]), block_means100(cols[4:])])
    assert np.array_equal(whole, parts)

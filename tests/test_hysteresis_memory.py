"""Hysteresis memories of close-the-loop (issue 12): the relay on the temperature path, the memory's
state at the start of a run (inferred from the run's own temperatures by a rule chosen on TRAIN), and
the search telling the start rules apart."""
from __future__ import annotations

import numpy as np
import pytest

from bench.fit import effects as fx
from bench.fit.closeloop_search import FINE_S, SearchProblem, evidence_blocks


def _inputs(time_s: np.ndarray, temp: np.ndarray) -> fx.Inputs:
    return fx.Inputs(time=time_s, temps={"t1": temp}, rates={"t1": fx.rate_c_per_min(temp, time_s, 300.0)},
                     since_on=time_s - time_s[0], power_known=False, up=None, input_rate=None)


def test_rate_relay_latches_past_the_threshold_and_holds_through_missing_rates():
    nan = np.nan
    rate = np.array([0.0, 0.05, 0.1, 0.2, 0.05, nan, -0.1, -0.3, nan, 0.0, 0.15, -0.1])
    got = fx.relay_state(rate, 0.1)          # exactly at the threshold does not switch
    np.testing.assert_array_equal(got, [0, 0, 0, 1, 1, 1, 1, -1, -1, -1, 1, 1])
    assert fx.relay_state(np.array([nan, nan]), 0.1).tolist() == [0.0, 0.0]
    assert len(fx.relay_state(np.zeros(0), 0.1)) == 0


def test_reversal_relay_switches_after_a_reversal_of_one_width():
    x = np.array([0.0, 1.0, 2.0, 4.0, 8.0, 10.0, 8.0, 7.5, 6.0, 2.0, 4.0, 6.0, 7.0])
    got = fx.reversal_relay_state(x, 3.0, -1.0)
    # rises 3 above the minimum 0 (level 3, half-way through the step 2 -> 4): -1 -> +1 with the step
    # shared; falls 3 below the maximum 10 (level 7, two thirds into 7.5 -> 6): to -1; rises 3 above 2
    # (level 5, half-way through 4 -> 6): to +1
    np.testing.assert_allclose(got, [-1, -1, -1, 0, 1, 1, 1, 1, -1 / 3, -1, -1, 0, 1])
    # started on the branch it is driven to, it holds until the first reversal
    np.testing.assert_array_equal(fx.reversal_relay_state(x, 3.0, 1.0)[:8], np.ones(8))
    # the state's share of a step moves continuously with the width
    a, b = fx.reversal_relay_state(x, 3.0, -1.0)[3], fx.reversal_relay_state(x, 3.2, -1.0)[3]
    assert a - b == pytest.approx(0.2)


def test_a_neutral_reversal_relay_holds_neither_branch_until_the_first_move_of_one_width():
    x = np.array([20.0, 21.0, 22.0, 21.5, 20.5, 19.0, 18.0, 19.0, 21.5, 22.0])
    got = fx.reversal_relay_state(x, 2.5, 0.0)
    # no move of 2.5 C from the start's extremes until 19.0 (the level 19.5, 2.5 below the high of
    # 22.0, is crossed a third of the way before the end of the step 20.5 -> 19.0: 0 -> -1 shared)
    np.testing.assert_array_equal(got[:5], np.zeros(5))
    assert got[5] == pytest.approx(-1.0 / 3.0) and got[6] == -1.0
    # then heating: 2.5 above the new low (18.0) is 20.5, crossed within the step 19.0 -> 21.5
    assert got[7] == -1.0 and got[8] == pytest.approx(-1.0 + 2.0 * (1.0 / 2.5)) and got[9] == 1.0


def test_relay_state_is_fixed_by_the_temperature_path_after_the_first_excursion():
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.normal(0, 0.3, 5000))
    w = 2.0
    first = int(np.flatnonzero(np.abs(x - x[0]) >= w)[0])
    up, down = fx.reversal_relay_state(x, w, 1.0), fx.reversal_relay_state(x, w, -1.0)
    np.testing.assert_array_equal(up[first + 1:], down[first + 1:])
    assert np.any(up[:first] != down[:first])


def test_start_rules_read_the_first_excursion_of_one_width():
    x = np.array([20.0, 19.5, 19.0, 20.5, 23.0, 30.0])      # the first move of 2 C is upwards
    assert fx.first_excursion_sign(x, 2.0) == 1.0
    assert fx.first_excursion_sign(x, 0.5) == -1.0         # of 0.5 C: downwards
    assert fx.memory_start("reversed", x, 2.0) == -1.0
    assert fx.memory_start("continued", x, 2.0) == 1.0
    assert fx.memory_start("neutral", x, 2.0) == 0.0
    with pytest.raises(ValueError, match="start rule 'sideways'"):
        fx.memory_start("sideways", x, 2.0)


def test_duhem_start_decays_with_the_temperature_travel():
    t = np.arange(0.0, 20000.0, FINE_S)
    temp = np.interp(t, [0, 4000, 9000, 20000], [20, 20, 35, 10])
    rate = fx.rate_c_per_min(temp, t, 300.0)
    w = 4.0
    dT = rate * FINE_S / 60.0
    travel = np.cumsum(np.abs(dT))
    got = fx.duhem_state(rate, t, w, -1.0) - fx.duhem_state(rate, t, w, 0.0)
    np.testing.assert_allclose(got, -np.exp(-travel / w), atol=1e-12)


@pytest.mark.parametrize("form,start", [("reversal", "reversed"), ("gradual", "reversed"), ("reversal", "continued")])
def test_training_search_chooses_the_start_rule_and_width(form, start):
    t = np.arange(5.0, 60000.0, FINE_S)
    temp = np.interp(t, [0, 6000, 14000, 20000, 30000, 38000, 46000, 60000], [20, 20, 45, 45, 5, 30, 12, 40])
    fine = _inputs(t, temp)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    fams = [f for f in fx.families(ctx, fine) if f.kind == "hysteresis" and dict(f.fixed).get("form") == form]
    truth = next(f for f in fams if dict(f.fixed).get("start") == start)
    width = 5.0
    rng = np.random.default_rng(11)
    y = 0.3 * truth.at(width).columns(fine)[next(iter(truth.at(width).columns(fine)))] + rng.normal(0, 0.01, len(t))
    ev = evidence_blocks(t, {"y": y, "one": np.ones(len(t))})
    problem = SearchProblem(yb=ev["y"], Xb=ev["one"][:, None], fine=fine,
                            declared_signals_b=np.zeros((len(ev["y"]), 0)), families=fams)
    fits = {f.label: problem.best_value(f, ()) for f in fams}
    best = min(fits, key=lambda k: fits[k][1])
    assert best == truth.label
    assert fits[best][0].value == pytest.approx(width, rel=0.1)


def _readings(t: np.ndarray, temp: np.ndarray, seed: int) -> np.ndarray:
    """A DS18B20-like probe: read noise, 0.0625 C steps."""
    rng = np.random.default_rng(seed)
    return np.round((temp + rng.normal(0, 0.02, len(t))) / 0.0625) * 0.0625


def test_the_temperature_path_moves_no_memory_in_a_soak_and_follows_a_ramp():
    t = np.arange(0.0, 30000.0)
    temp = np.interp(t, [0, 4000, 14000, 30000], [20, 20, 45, 45])
    path = fx.temperature_path(t, _readings(t, temp, 1))
    soak, ramp = (t > 15000), (t > 4500) & (t < 13500)
    assert np.sum(np.abs(np.diff(path[soak]))) < 0.05          # noise and steps held in the dead band
    assert np.sum(np.abs(np.diff(path[ramp]))) == pytest.approx(np.ptp(temp[ramp]), abs=0.1)
    assert np.max(np.abs(path - temp)) < 0.1
    # the readings themselves would drive a Duhem memory through the soak's noise: it decays to 0
    assert abs(fx.duhem_memory(_readings(t, temp, 1), 4.0)[-1]) < 0.5 < fx.duhem_memory(path, 4.0)[-1]


def test_a_memory_of_the_path_is_carried_across_a_recording_outage():
    t = np.arange(0.0, 40000.0)
    temp = np.interp(t, [0, 3000, 15000, 22000, 40000], [20, 20, 44, 44, 10])
    x = _readings(t, temp, 2)
    keep = np.ones(len(t), dtype=bool)
    keep[8000:11000] = False                                   # 50 min missing mid-ramp
    keep[30000:30400] = False
    full, gappy = fx.temperature_path(t, x), fx.temperature_path(t[keep], x[keep])
    for width in (1.0, 5.0):
        for memory in (fx.duhem_memory, fx.play_memory):
            # equal but for the readings' noise at the outage's edges (the mean there is over fewer readings)
            np.testing.assert_allclose(memory(gappy, width, -1.0), memory(full, width, -1.0)[keep], atol=0.06)
            # the relay: the same switches (a switching sample may share its step differently)
            relay_gap = fx.reversal_relay_state(gappy, width, -1.0)
            relay_full = fx.reversal_relay_state(full, width, -1.0)[keep]
            assert np.sum(np.abs(relay_gap - relay_full) > 0.06) <= 3
    # a memory driven by the filtered rate stops over the outage while the temperature moves on
    rate = fx.rate_c_per_min(x[keep], t[keep], 300.0)
    after = int(np.searchsorted(t[keep], 11000))
    frozen = fx.duhem_state(rate, t[keep], 20.0, -1.0)[after]
    assert abs(frozen - fx.duhem_memory(full, 20.0, -1.0)[11000]) > 0.2


def test_play_memory_moves_one_for_one_after_a_reversal_and_saturates_after_one_width():
    x = np.array([0.0, 2.0, 6.0, 10.0, 9.0, 8.0, 6.0, 4.0, 5.0])
    m = fx.play_memory(x, 4.0)                                 # half width 2: m = (x - p) / 2
    np.testing.assert_allclose(m, [0.0, 1.0, 1.0, 1.0, 0.5, 0.0, -1.0, -1.0, -0.5])
    np.testing.assert_allclose(fx.play_memory(x, 4.0, -1.0)[:3], [-1.0, 0.0, 1.0])


def test_the_joint_refit_finds_a_memory_delay_and_charges_it():
    t = np.arange(5.0, 60000.0, FINE_S)
    temp = np.interp(t, [0, 6000, 14000, 20000, 30000, 38000, 46000, 60000], [20, 20, 45, 45, 5, 30, 12, 40])
    fine = _inputs(t, temp)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    fam = next(f for f in fx.families(ctx, fine)
               if dict(f.fixed).get("form") == "reversal" and dict(f.fixed).get("start") == "reversed")
    assert fam.delayed and fam.with_delay(90.0) == fam and fam.with_delay(90.0).label == fam.label
    assert fam.with_delay(90.0).at(3.0).label != fam.at(3.0).label          # the column cache's key
    truth = fam.with_delay(90.0).at(3.0)
    rng = np.random.default_rng(5)
    y = 0.3 * next(iter(truth.columns(fine).values())) + rng.normal(0, 0.01, len(t))
    ev = evidence_blocks(t, {"y": y, "one": np.ones(len(t))})
    problem = SearchProblem(yb=ev["y"], Xb=ev["one"][:, None], fine=fine,
                            declared_signals_b=np.zeros((len(ev["y"]), 0)), families=[fam])
    scanned, _ = problem.best_value(fam, ())
    assert scanned.family.delay_s == 0.0                       # candidates are scanned at their delay
    got, _ = problem.best_value(fam, (), refine_delay=True)
    assert got.family.delay_s == pytest.approx(90.0, abs=15.0)
    assert got.value == pytest.approx(3.0, rel=0.05)
    assert got.params["delay_s"] == pytest.approx(got.family.delay_s, abs=1.0)
    # the delay is a searched parameter: one more ln(n_eff) than the width alone
    plain = fx.Family("hysteresis", fam.fixed, fam.builder, "width_c", fam.grid, chosen_probe=False,
                      variants=fam.variants)
    assert fam.penalty(100.0) - plain.penalty(100.0) == pytest.approx(np.log(100.0))


def _memory_run(profile, start_rule: str, seed: int):
    """A unit whose bias carries a play memory (width 5 C, on t1) that begins the run under
    ``start_rule``: the history before the record, which no column shows."""
    from bench.fit.base import Dataset
    from tests.synth import DT, chamber_profile

    rng = np.random.default_rng(seed)
    t, air = chamber_profile(profile, dt=DT)
    true_t1 = fx.first_order_lag(air, t, 600.0)
    t1 = np.round((true_t1 + rng.normal(0, 0.005, len(t))) / 0.0625) * 0.0625
    t2 = np.round(fx.first_order_lag(air, t, 1500.0) / 0.0625) * 0.0625
    memory = fx.play_memory(true_t1, 5.0, fx.memory_start(start_rule, true_t1, 5.0))
    u = true_t1 - 25.0
    y = 0.1 + 0.02 * u + 4e-4 * u ** 2 + 0.4 * memory + rng.normal(0, 0.08, len(t))
    cols = {"time_s": t, "temp_t1": t1, "temp_t2": t2, "gyro_x": y}
    return Dataset(cols, {"gyro_id": "SYN-MEM", "sample_period_s": str(DT)}), memory


def test_a_memory_starts_the_validation_run_in_the_state_that_run_shows_its_coefficients_as_trained():
    from bench.fit.closeloop import close_loop
    from tests.synth import TRAIN_PROFILE, VALIDATE_PROFILE

    # the training run began as if it continued its first excursion, the validation run from neutral
    train, m_tr = _memory_run(TRAIN_PROFILE, "continued", 21)
    validate, m_va = _memory_run(VALIDATE_PROFILE, "neutral", 22)
    report = close_loop(train, validate, "t1 + t1^2", channels=["x"], bin_c=None)
    ch = report["channels"]["x"]
    (memory,) = ch["effects_added"]
    assert memory["kind"] == "hysteresis" and memory["params"]["probe"] == "t1"
    assert memory["params"]["start"] == "continued"
    assert memory["start_on_validation"] == "neutral"
    assert "starts the validation run neutral" in ch["findings"]
    from bench.fit.closeloop_report import render_close_loop_report
    page = render_close_loop_report(report, train, validate)
    assert "start on validation=neutral" in page[page.index("effects added"):]
    # the validation error is the true model's (declared terms and the true memory fitted on TRAIN)
    X = lambda run, m: np.column_stack([np.ones(len(m)), run.columns["temp_t1"], run.columns["temp_t1"] ** 2, m])
    beta = np.linalg.lstsq(X(train, m_tr), train.columns["gyro_x"], rcond=None)[0]
    from bench.fit.closeloop import std100
    oracle = std100(validate.columns["gyro_x"] - X(validate, m_va) @ beta, validate.time)
    assert ch["after"]["validation_std100_dph"] < 1.15 * oracle
    assert ch["verdict"] == "explained"
    # both runs begin under the same rule: the trained start is kept
    same, _ = _memory_run(VALIDATE_PROFILE, "continued", 22)
    ch = close_loop(train, same, "t1 + t1^2", channels=["x"], bin_c=None)["channels"]["x"]
    assert [e["params"].get("start") for e in ch["effects_added"]] == ["continued"]
    assert "start_on_validation" not in ch["effects_added"][0]


def _relay_one_step_at_a_time(x: np.ndarray, width_c: float, start: float) -> np.ndarray:
    """The reversal relay's definition, sample by sample (the reference the array version must match)."""
    out, s = np.empty(len(x)), float(np.sign(start))
    hi = lo = prev = float(x[0])
    for i, v in enumerate(x.tolist()):
        o = None
        hi, lo = max(hi, v), min(lo, v)
        if s >= 0 and hi - v >= width_c:
            level = hi - width_c
            after = (level - v) / (prev - v) if prev > v and prev > level else 1.0
            s, lo, o = -1.0, v, s - (s + 1.0) * after
        elif s <= 0 and v - lo >= width_c:
            level = lo + width_c
            after = (v - level) / (v - prev) if v > prev and prev < level else 1.0
            s, hi, o = 1.0, v, s + (1.0 - s) * after
        out[i] = s if o is None else o
        prev = v
    return out


def _play_one_step_at_a_time(x: np.ndarray, h: float, p0: float) -> np.ndarray:
    out, p = np.empty(len(x)), p0
    for i, v in enumerate(x.tolist()):
        if v - h > p:
            p = v - h
        elif v + h < p:
            p = v + h
        out[i] = p
    return out


@pytest.mark.parametrize("seed", range(6))
def test_the_relay_and_play_memories_equal_their_step_by_step_definitions(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 20000))
    # soaks, ramps and reversals with reading noise: long stretches without a switch and bursts of
    # switching (a width near the noise)
    x = np.cumsum(rng.normal(0, 0.05, n)) + 10 * np.sin(np.arange(n) / rng.uniform(50, 3000)) + rng.normal(0, 0.02, n)
    for width in (0.01, 0.1, 1.0, 5.0, 50.0):
        for start in (-1.0, 0.0, 1.0):
            np.testing.assert_array_equal(fx.reversal_relay_state(x, width, start),
                                          _relay_one_step_at_a_time(x, width, start))
            p0 = float(x[0]) - start * width / 2
            np.testing.assert_array_equal(fx._backlash(x, width / 2, p0), _play_one_step_at_a_time(x, width / 2, p0))
    assert len(fx.reversal_relay_state(np.zeros(0), 1.0, 1.0)) == 0 and len(fx._backlash(np.zeros(0), 1.0, 0.0)) == 0


def test_whole_powers_match_numpys_power_to_the_last_bits_and_keep_the_sign():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(0.0, 10.0, 2000), [0.0, -0.0, np.nan, -2.5, 2.5]])
    for j in range(1, 6):
        got, ref = fx.whole_power(x, j), x ** j
        np.testing.assert_array_max_ulp(got[np.isfinite(ref)], ref[np.isfinite(ref)], maxulp=2)
        assert np.array_equal(np.signbit(got), np.signbit(ref)) and np.isnan(got[-3])
    assert fx.whole_power(np.array([-2.5]), 3)[0] == -15.625 and fx.whole_power(np.array([-2.5]), 2)[0] == 6.25

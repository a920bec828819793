"""Close-the-loop method details (issue 12): block means over measured samples only, parameter
refinement beyond the scan grid, the noise floor's degrees of freedom under flicker noise, and the
cross-validation entry of the report when blocked cross-validation cannot judge an effect."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from bench.fit import effects as fx
from bench.fit.closeloop import close_loop
from bench.fit.closeloop_report import render_close_loop_report
from bench.fit.closeloop_search import (CV_CONFINED, FINE_S, SearchProblem, centre_stepwise, cv_gain_text,
                                        evidence_blocks)
from bench.fit.noisefloor import NoiseModel, barnes_b1, block_means_edf
from bench.signal import BlockPlan, block_means
from tests.synth import TRAIN_PROFILE, VALIDATE_PROFILE, make_run


def _inputs(time_s: np.ndarray, temp: np.ndarray, since_on: np.ndarray | None = None) -> fx.Inputs:
    since = time_s - time_s[0] if since_on is None else since_on
    return fx.Inputs(time=time_s, temps={"t1": temp}, rates={"t1": fx.rate_c_per_min(temp, time_s, 300.0)},
                     since_on=since, power_known=since_on is not None, up=None, input_rate=None)


def _problem(fine: fx.Inputs, y_fine: np.ndarray, families: list[fx.Family]) -> SearchProblem:
    ev = evidence_blocks(fine.time, {"y": y_fine, "one": np.where(np.isfinite(y_fine), 1.0, np.nan)})
    return SearchProblem(yb=ev["y"], Xb=ev["one"][:, None], fine=fine, declared_signals_b=np.zeros((len(ev["y"]), 0)),
                         families=families, fine_valid=np.isfinite(y_fine))


def test_block_plan_gives_the_same_blocks_as_block_means():
    rng = np.random.default_rng(1)
    t = np.concatenate([np.arange(0.0, 1234.0, 1.0), np.arange(5000.0, 5777.0, 1.0)])
    segments = [slice(0, 1234), slice(1234, len(t))]
    a = rng.normal(size=len(t))
    a[rng.random(len(t)) < 0.1] = np.nan
    ref = block_means(t, {"a": a}, 100.0, segments)
    plan = BlockPlan(t, 100.0, segments)
    np.testing.assert_array_equal(plan.means(a), ref.columns["a"])
    np.testing.assert_array_equal(plan.time_s, ref.time_s)
    assert plan.segments == ref.segments
    np.testing.assert_array_equal(plan.first_index, ref.first_index)


def test_regressor_block_means_use_only_the_samples_where_the_target_was_measured():
    # the gyro is off for the first 60 s of a 100-s block: the warm-up column must be averaged over
    # the 40 s the target was measured, not diluted by the zeros of the off part
    t = np.arange(5.0, 3000.0, FINE_S)
    since = np.where(t < 1060.0, np.nan, t - 1060.0)
    since[t < 500.0] = t[t < 500.0]
    fine = _inputs(t, np.full(len(t), 20.0), since)
    family = fx.Family("warmup", (), lambda x, tau: {"w": np.nan_to_num(np.exp(-x.since_on / tau), nan=0.0)},
                       "tau_s", (100.0, 200.0, 400.0))
    y = np.where(np.isfinite(since), 3.0 * np.exp(-np.nan_to_num(since) / 200.0), np.nan)
    problem = _problem(fine, y, [family])
    col = problem.columns(family.at(200.0))[:, 0]
    ok = np.isfinite(problem.yb)
    # the column's block means follow the target's exactly (the target is 3 x the column)
    np.testing.assert_allclose(problem.yb[ok], 3.0 * col[ok], rtol=1e-12)
    assert problem.ssr((family.at(200.0),)) < 1e-20


def test_a_parameter_beyond_the_end_of_the_scan_grid_is_still_found():
    t = np.arange(5.0, 40000.0, FINE_S)
    temp = np.interp(t, [0, 5000, 12000, 20000, 27000, 40000], [20, 50, 50, 0, 0, 30])
    fine = _inputs(t, temp)
    family = fx.Family("hysteresis", (("probe", "t1"), ("form", "gradual")),
                       lambda x, w: {"m": fx.duhem_state(x.rates["t1"], x.time, w)}, "width_c", (1.0, 2.0, 4.0, 8.0))
    assert family.bounds == (0.5, 16.0)
    truth = 0.6
    y = 0.5 * fx.duhem_state(fine.rates["t1"], t, truth)
    best, ssr = _problem(fine, y, [family]).best_value(family, ())
    assert best.value == pytest.approx(truth, rel=0.05)
    limited = fx.Family("warmup", (), family.builder, "tau_s", (1.0, 2.0), limits=(0.8, 3.0))
    assert limited.bounds == (0.8, 3.0)
    # a thermal lag is not refined below the grid's first time constant: shorter, it is a rate
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    lags = [f for f in fx.families(ctx, fine) if f.kind == "thermal_lag"]
    assert lags and all(f.bounds[0] == fx.LAG_TAUS_S[0] for f in lags)
    # ... nor beyond twice the record: slower, it is the temperature's running integral
    short = _inputs(t[t < 10_800], temp[t < 10_800])
    span = short.time[-1] - short.time[0]
    settled = lambda f: dict(f.fixed).get("initial") != "unsettled"
    capped = [f for f in fx.families(ctx, short) if f.kind == "thermal_lag" and settled(f)]
    assert all(f.bounds[1] == pytest.approx(2.0 * span) for f in capped)
    assert all(max(f.grid) <= f.bounds[1] for f in capped) and 14400.0 in capped[0].grid
    assert all(f.bounds[1] == fx.LAG_LIMITS_S[1] for f in lags if settled(f))      # 11.1 h: the cap is not reached
    # where the record's length sets the limit, a lag wanting it is no lag (``open_end``); where the
    # grid's own limit binds, it is a long lag
    assert all(f.open_above for f in capped) and not any(f.open_above for f in lags if settled(f))
    # the unsettled form (this probe ramps at the run's start) only where its start offset decays in the run
    unsettled = [f for f in fx.families(ctx, short) if f.kind == "thermal_lag" and not settled(f)]
    assert unsettled and all(f.bounds[1] == pytest.approx(span / fx.LAG_START_SPANS) for f in unsettled)
    assert all(max(f.grid) <= f.bounds[1] for f in unsettled)
    # another probe's temperature lagged as it is: from three evidence blocks up (faster, a gradient)
    two = fx.Context(channel="x", primary_probe="t1", probes=("t1", "t2"), channels=("x",), latitude_deg=None)
    other = fx.Inputs(time=t, temps={"t1": temp, "t2": temp + 0.5},
                      rates={p: fx.rate_c_per_min(temp, t, 300.0) for p in ("t1", "t2")},
                      since_on=t - t[0], power_known=False, up=None, input_rate=None)
    absolute = [f for f in fx.families(two, other) if f.kind == "thermal_lag" and dict(f.fixed).get("form") == "absolute"]
    assert [dict(f.fixed)["probe"] for f in absolute] == ["t2"]
    assert absolute[0].bounds[0] == fx.ABSOLUTE_LAG_MIN_S and min(absolute[0].grid) >= fx.ABSOLUTE_LAG_MIN_S


def _excursions_and_memory(open_above: bool) -> tuple[fx.Inputs, fx.Family]:
    """A run of two excursions (20 -> 50 -> 0 -> 30 C) and a gradual memory on it whose width is limited
    to 8 C (``open_above``: that limit is where the memory stops being one)."""
    t = np.arange(5.0, 40000.0, FINE_S)
    temp = np.interp(t, [0, 5000, 12000, 20000, 27000, 40000], [20, 50, 50, 0, 0, 30])
    family = fx.Family("hysteresis", (("probe", "t1"), ("form", "gradual")),
                       lambda x, w, delay=0.0: {"m": fx.duhem_memory(x.path("t1", delay), w)}, "width_c",
                       (1.0, 2.0, 4.0, 8.0), limits=(0.5, 8.0), delayed=True, open_above=open_above)
    return _inputs(t, temp), family


def test_a_memorys_width_stays_within_its_meaningful_range_when_its_delay_is_profiled():
    # the data want a memory wider than the family allows (a wider one never saturates on this run): the
    # joint re-fit, which profiles the delay with the width re-fitted at each delay, must not leave the
    # range either (it once returned 30.7 C for a family limited to 27 C)
    fine, family = _excursions_and_memory(open_above=False)
    y = 0.5 * fx.duhem_memory(fine.path("t1", 60.0), 14.0)
    problem = _problem(fine, y, [family])
    plain, _ = problem.best_value(family, ())
    profiled, _ = problem.best_value(family, (), refine_delay=True)
    assert plain.value <= 8.0 and plain.value == pytest.approx(8.0, rel=0.05)
    assert profiled.value <= 8.0 + 1e-9


def test_a_gradual_memory_the_data_want_wider_than_half_the_span_is_no_candidate():
    # a memory as wide as half the probe's span barely saturates within the run: when the fit wants it
    # at least that wide (open_above), the fit is a drift along the temperature's travel and the family
    # fills no place (infinite cost, plain or with its delay profiled); a memory inside the range is kept
    fine, family = _excursions_and_memory(open_above=True)
    wide = _problem(fine, 0.5 * fx.duhem_memory(fine.path("t1", 60.0), 14.0), [family])
    for refine in (False, True):
        eff, cost = wide.best_value(family, (), refine_delay=refine)
        assert family.open_end(eff.value) and cost == float("inf")
    inside = _problem(fine, 0.5 * fx.duhem_memory(fine.path("t1", 0.0), 3.0), [family])
    eff, cost = inside.best_value(family, ())
    assert eff.value == pytest.approx(3.0, rel=0.1) and np.isfinite(cost) and not family.open_end(eff.value)


def test_a_lag_the_data_want_at_twice_the_record_is_no_candidate():
    # a 3-h run that starts at its warmest and stays below: the running integral of the temperature is
    # about linear in time, so a time drift is fitted by a lag as slow as the family allows (twice the
    # record), which is not a time constant the run tells.  A lag inside the range is found as it is
    t = np.arange(5.0, 10_800.0, FINE_S)
    temp = np.interp(t, [0, 1500, 4000, 6500, 9000, 10_800], [50, 48, 20, 35, 15, 30])
    fine = _inputs(t, temp)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    lag = next(f for f in fx.families(ctx, fine) if f.kind == "thermal_lag" and not dict(f.fixed).get("form")
               and not dict(f.fixed).get("initial"))
    drift = _problem(fine, 0.2 * (t - t[0]) / 3600.0, [lag])
    eff, cost = drift.best_value(lag, ())
    assert lag.open_end(eff.value) and cost == float("inf")
    tau = 1800.0
    inside = _problem(fine, 0.05 * (fx.first_order_lag(temp, t, tau) - temp), [lag])
    eff, cost = inside.best_value(lag, ())
    assert eff.value == pytest.approx(tau, rel=0.05) and np.isfinite(cost) and not lag.open_end(eff.value)


def test_a_relay_threshold_the_training_run_pins_only_to_an_interval_is_taken_at_its_middle():
    # the training run ramps at 0.1 and 0.5 C/min only: every threshold in [0.1, 0.5) switches the
    # relay at the same instants, so the run says no more than that; the middle of that interval in
    # log scale, sqrt(0.1 x 0.5), is taken, not the first value the scan met
    t = np.arange(5.0, 60000.0, FINE_S)
    rate = np.select([(t % 12000) < 3000, (t % 12000) < 6000, (t % 12000) < 9000],
                     [0.5, -0.1, 0.1], -0.5)
    fine = fx.Inputs(time=t, temps={"t1": np.cumsum(rate) * FINE_S / 60.0}, rates={"t1": rate},
                     since_on=t - t[0], power_known=False, up=None, input_rate=None)
    relay = fx.Family("hysteresis", (("probe", "t1"), ("form", "relay")),
                      lambda x, thr: {"r": fx.relay_state(x.rates["t1"], thr)}, "threshold_c_per_min",
                      fx.RELAY_THRESHOLDS, stepwise=True)
    problem = _problem(fine, 0.8 * fx.relay_state(rate, 0.3), [relay])
    best, _ = problem.best_value(relay, ())
    assert 0.1 <= best.value < 0.5
    (centred,) = centre_stepwise(problem, (best,))
    assert centred.value == pytest.approx(np.sqrt(0.1 * 0.5), rel=0.02)
    assert problem.ssr((centred,)) == pytest.approx(problem.ssr((best,)), abs=1e-20)
    # a parameter whose columns change continuously is left where the search put it
    smooth = replace(relay, stepwise=False)
    assert centre_stepwise(problem, (smooth.at(0.12),))[0].value == 0.12


def test_block_means_edf_is_exact_for_white_noise_and_small_under_flicker():
    assert block_means_edf(100, {-1.0: 1.0}) == pytest.approx(99.0)
    flicker = block_means_edf(288, {0.0: 1.0})
    assert 20.0 < flicker < 0.5 * 287 / barnes_b1(288, 0.0)


def test_flicker_floor_interval_covers_the_scatter_of_simulated_records():
    # flicker (1/f) rate noise shaped in the frequency domain: its std of 100-s means over 8 h
    # scatters far more than white noise's; the floor's 90 % interval must cover about 90 % of it
    rng = np.random.default_rng(7)
    n, dt = 28800, 1.0
    f = np.fft.rfftfreq(n, dt)
    shape = np.zeros_like(f)
    shape[1:] = 1.0 / np.sqrt(f[1:])
    stds = []
    for _ in range(200):
        x = np.fft.irfft(np.fft.rfft(rng.normal(size=n)) * shape, n)
        stds.append(np.std(x.reshape(-1, 100).mean(axis=1), ddof=1))
    stds = np.array(stds)
    # the model: flicker only, its Allan variance level set from the mean of the simulated records
    h0 = np.mean(stds ** 2) / barnes_b1(288, 0.0)
    model = NoiseModel(coef={0.0: h0}, taus=np.array([100.0]), adev=np.array([np.sqrt(h0)]), tau_max_s=100.0)
    fl = model.floor(n * dt)
    lo, hi = fl["interval_dph"]
    inside = np.mean((stds >= lo) & (stds <= hi))
    assert 0.8 <= inside <= 0.97, (inside, fl)
    assert fl["limit_dph"] > hi
    assert np.mean(stds > fl["limit_dph"]) <= 0.04
    assert fl["limit_dph"] == pytest.approx(fl["noise_floor_dph"] * np.sqrt(chi2.ppf(0.99, fl["edf"]) / fl["edf"]))


def test_cross_validation_entry_says_why_it_does_not_apply():
    assert cv_gain_text({"cv_gain": 0.254}) == "-25 %"
    assert cv_gain_text({"cv_gain": float("nan"), "cv_not_applicable": CV_CONFINED}) == f"n/a ({CV_CONFINED})"
    assert cv_gain_text({"cv_gain": float("nan")}).startswith("n/a (")


def test_html_effects_table_never_prints_nan_for_cross_validation():
    train, _ = make_run(TRAIN_PROFILE, {"gradient": 0.06}, seed=3)
    validate, _ = make_run(VALIDATE_PROFILE, {"gradient": 0.06}, seed=4)
    report = close_loop(train, validate, "static", channels=["x"], bin_c=None)
    ch = report["channels"]["x"]
    assert ch["effects_added"], ch["findings"]
    for e in ch["effects_added"]:
        e["evidence"]["cv_gain"] = float("nan")
        e["evidence"]["cv_not_applicable"] = CV_CONFINED
    page = render_close_loop_report(report, train, validate)
    table = page[page.index("effects added"):]
    table = table[: table.index("</table>")]
    assert "nan" not in table and f"n/a ({CV_CONFINED})" in table


def _twins_and_a_drift(seed: int, drift_per_hour: float) -> SearchProblem:
    # a lag and a "gradient" with the same column (no data tells them apart) beside a time drift
    rng = np.random.default_rng(seed)
    t = np.arange(5.0, 40_000.0, FINE_S)
    temp = 20.0 * np.sin(t / 4000.0) + 5.0 * np.sin(t / 1300.0)
    lagged = fx.first_order_lag(temp, t, 900.0) - temp
    twin = lambda name: fx.Family(name, (("probe", "t1"),), lambda x, _v: {name: lagged}, chosen_probe=False)
    drift = fx.Family("time_drift", (), lambda x, _v: {"t_hours": (x.time - x.time[0]) / 3600.0})
    y = 0.05 * lagged + drift_per_hour * (t - t[0]) / 3600.0 + rng.normal(0, 0.02, len(t))
    return _problem(_inputs(t, temp), y, [twin("thermal_lag"), twin("gradient"), drift])


def test_two_candidates_the_training_run_cannot_tell_apart_are_named_as_an_ambiguity():
    from bench.fit.closeloop_search import AMBIGUOUS_DBIC, search

    chosen, steps = search(_twins_and_a_drift(7, 0.0))
    assert len(chosen) == 1
    ev = steps[0]["evidence"]
    names = {a["kind"] for a in ev["ambiguous_with"]}
    assert names == {"thermal_lag", "gradient"} - {chosen[0].kind}
    assert all(0 <= a["bic_margin"] < AMBIGUOUS_DBIC for a in ev["ambiguous_with"])


def test_each_member_of_a_model_is_named_with_what_the_training_run_cannot_tell_from_it():
    # two effects, one of them with a twin no data can tell from it: the twin is named beside that
    # member in the final model, whether the search took the two in one step or one after the other
    from bench.fit.closeloop_search import AMBIGUOUS_DBIC, lookalikes, search

    problem = _twins_and_a_drift(11, 0.01)
    chosen, _ = search(problem)
    assert sorted(e.kind for e in chosen) in (["gradient", "time_drift"], ["thermal_lag", "time_drift"])
    named = {e.kind: [a["kind"] for a in alike] for e, alike in zip(chosen, lookalikes(problem, chosen))}
    lag_kind = next(k for k in named if k != "time_drift")
    assert named == {lag_kind: [{"thermal_lag", "gradient"}.difference({lag_kind}).pop()], "time_drift": []}
    assert all(abs(a["bic_margin"]) < AMBIGUOUS_DBIC for alike in lookalikes(problem, chosen) for a in alike)


def _drift_problem(y: np.ndarray, t: np.ndarray) -> SearchProblem:
    fine = _inputs(t, np.full(len(t), 20.0))
    drift = fx.Family("time_drift", (), lambda x, _v: {"t_hours": (x.time - x.time[0]) / 3600.0})
    return _problem(fine, y, [drift])


def test_a_bias_step_is_not_taken_for_a_time_drift():
    from bench.fit.closeloop_search import search

    rng = np.random.default_rng(11)
    t = np.arange(5.0, 36_000.0, FINE_S)
    noise = rng.normal(0, 0.02, len(t))
    # one abrupt change at 6.1 h: a drift fits part of it, a step at the right time fits it all
    chosen, steps = search(_drift_problem(0.05 * (t >= 22_000.0) + noise, t))
    assert chosen == ()
    found = [s["time_drift_is_a_step"] for s in steps if "time_drift_is_a_step" in s]
    assert len(found) == 1 and abs(found[0]["step_at_s"] - 22_000.0) <= 200.0
    assert found[0]["step_dph"] == pytest.approx(0.05, rel=0.1)
    # a steady drift of the same overall size stays a drift
    chosen, steps = search(_drift_problem(0.05 * t / 36_000.0 + noise, t))
    assert [e.kind for e in chosen] == ["time_drift"]
    assert not any("time_drift_is_a_step" in s for s in steps)


def test_no_scale_factor_term_when_the_input_rate_never_changes():
    # one static position: the Earth rate along the channel, recomputed per sample, is one value up to
    # rounding; w_in * (T - 25) is then a plain temperature term, not a scale factor
    t = np.arange(0.0, 20000.0, 1.0)
    temp = 20.0 + 15.0 * np.sin(t / 3000.0)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=48.1)
    earth = np.full(len(t), 10.044915307032468) * np.cos(np.zeros(len(t)))   # one value, rounding aside
    earth[::7] += 1.8e-15
    assert np.nanstd(earth) > 0
    static = replace(_inputs(t, temp), input_rate=earth)
    assert not any(f.kind == "scale_factor_temperature" for f in fx.families(ctx, static))
    turning = replace(_inputs(t, temp), input_rate=earth + 3600.0 * np.where(t > 10000.0, 2.0, 0.0))
    assert any(f.kind == "scale_factor_temperature" for f in fx.families(ctx, turning))


def test_structure_the_model_misses_on_the_validation_run_does_not_raise_its_noise_floor():
    # the same unit on both runs; on the validation run a bias that switches every 15 min, which no
    # column records (a relay the model has in the wrong state there looks the same): read as noise it
    # would lift the floor towards it
    train, _ = make_run(TRAIN_PROFILE, {}, seed=11)
    clean, _ = make_run(VALIDATE_PROFILE, {}, seed=12)
    wavy, _ = make_run(VALIDATE_PROFILE, {}, seed=12)
    t = wavy.time
    wavy.columns["gyro_x"] = wavy.columns["gyro_x"] + 0.1 * np.sign(np.sin(2 * np.pi * (t - t[0]) / 1800.0 + 0.3))
    quiet = close_loop(train, clean, "static", channels=["x"], bin_c=None)["channels"]["x"]
    loud = close_loop(train, wavy, "static", channels=["x"], bin_c=None)["channels"]["x"]
    assert quiet["noise_floor"]["validation_residual_used"]
    assert not loud["noise_floor"]["validation_residual_used"]
    assert "train residual (" in loud["decisions"]["noise_floor"]
    # the floor stays the noise's: near the clean run's, far below the wave's std of 100-s means
    assert loud["noise_floor_dph"] < 1.2 * quiet["noise_floor_dph"]      # 1.44x with it read as noise
    assert loud["after"]["validation_std100_dph"] > 5 * loud["noise_floor_dph"]
    assert loud["verdict"] == "unexplained_structure_remains"


def _chosen_between(simple: fx.Family, rich: fx.Family, fine: fx.Inputs, y: np.ndarray) -> tuple[float, str]:
    """The training BIC margin of ``rich`` over ``simple`` (each at its best value) and the form the
    search takes, on a declared cubic in the probe."""
    from bench.fit.closeloop_search import search

    t, u = fine.time, fine.temps["t1"] - 25.0
    ev = evidence_blocks(t, {"y": y, "one": np.ones_like(t), "u1": u, "u2": u ** 2, "u3": u ** 3})
    problem = SearchProblem(yb=ev["y"], Xb=np.column_stack([ev[k] for k in ("one", "u1", "u2", "u3")]),
                            fine=fine, declared_signals_b=np.zeros((len(ev["y"]), 0)), families=[simple, rich],
                            fine_valid=np.isfinite(y))
    a, _ = problem.best_value(simple, ())
    b, _ = problem.best_value(rich, ())
    n_eff = problem.score((a,), with_cv=False).n_eff
    chosen, _steps = search(problem)
    assert len(chosen) == 1
    picked = chosen[0].family
    return problem.bic((a,), n_eff) - problem.bic((b,), n_eff), "rich" if picked == rich else "simple"


def _program() -> fx.Inputs:
    t = np.arange(5.0, 60_000.0, FINE_S)
    temp = np.interp(t, [0, 4000, 10000, 16000, 22000, 30000, 36000, 44000, 52000, 60000],
                     [20, 50, 50, 0, 0, 40, -10, -10, 30, 30])
    return _inputs(t, temp)


def test_the_declared_model_at_a_lagged_temperature_is_taken_over_the_linear_lag_only_on_strong_evidence():
    # f(lag T) - f(T), f the declared cubic's part in T as TRAIN fits it, is a more particular form of the
    # linear lag (lag - T) of the own probe: a training run that prefers it by less than DBIC_MIN keeps
    # the linear one
    from bench.fit.closeloop_search import DBIC_MIN, TIE_DBIC

    fine = _program()
    t, temp = fine.time, fine.temps["t1"]
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    assert not any(dict(f.fixed).get("form") == "polynomial"
                   for f in fx.families(replace(ctx, own_shape=(0.02,)), fine))   # a linear f: the linear lag
    lag = fx.first_order_lag(temp, t, 1500.0)

    def chosen(cubic: float) -> tuple[float, str]:
        # the unit's f: 0.02 (T - 25) + cubic (T - 25)^3, and its element 1500 s behind the probe
        lags = [f for f in fx.families(replace(ctx, own_shape=(0.02, 0.0, cubic)), fine) if f.kind == "thermal_lag"]
        linear = next(f for f in lags if f.fixed == (("probe", "t1"),))
        shape = next(f for f in lags if dict(f.fixed).get("form") == "polynomial")
        assert shape.contains(linear) and not linear.contains(shape)
        y = 0.02 * (lag - temp) + cubic * ((lag - 25.0) ** 3 - (temp - 25.0) ** 3)
        return _chosen_between(linear, shape, fine, y + np.random.default_rng(3).normal(0, 0.05, len(t)))

    margin, form = chosen(5e-7)         # a trace of curvature: the particular form fits better, not by much
    assert TIE_DBIC < margin < DBIC_MIN
    assert form == "simple"
    margin, form = chosen(2e-6)
    assert margin > DBIC_MIN
    assert form == "rich"


def test_a_cross_term_about_a_temperature_of_its_own_is_taken_over_the_rate_only_on_strong_evidence():
    # (T - T0) dT/dt with the unit's T0 unknown holds the rate dT/dt of that probe: a training run that
    # prefers it by less than DBIC_MIN keeps the rate
    from bench.fit.closeloop_search import DBIC_MIN, TIE_DBIC

    fine = _program()
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1",), channels=("x",), latitude_deg=None)
    fams = fx.families(ctx, fine)
    rate = next(f for f in fams if f.kind == "rate")
    cross = next(f for f in fams if f.kind == "temp_rate_cross")
    assert cross.contains(rate) and not rate.contains(cross)
    r = fx.rate_c_per_min(fine.temps["t1"], fine.time, 120.0)
    u = fine.temps["t1"] - 25.0

    def y(c: float) -> np.ndarray:
        return 0.05 * r + c * u * r + np.random.default_rng(3).normal(0, 0.05, len(r))

    margin, form = _chosen_between(rate, cross, fine, y(4e-4))
    assert TIE_DBIC < margin < DBIC_MIN
    assert form == "simple"
    margin, form = _chosen_between(rate, cross, fine, y(1e-3))
    assert margin > DBIC_MIN
    assert form == "rich"


def test_a_rate_window_the_training_run_does_not_determine_is_the_declared_models_own():
    # a rate effect on a noisy run: every window from 60 to 300 s fits the training run alike (within
    # TIE_DBIC), so the scan's minimum is set by the noise; the window is settled on the declared
    # model's own (120 s).  A run that pins the window (600 s, little noise) keeps it
    from bench.fit.closeloop_search import settle_rate_windows

    t = np.arange(5.0, 40_000.0, FINE_S)
    temp = np.interp(t, [0, 3000, 9000, 12000, 18000, 24000, 30000, 40000], [20, 50, 50, 0, 0, 40, -10, 30])
    fine = _inputs(t, temp)
    rate = fx.Family("rate", (("probe", "t1"),), lambda x, w: {"r": x.rate("t1", w)}, fx.RATE_WINDOW_PARAM,
                     fx.RATE_WINDOWS_S, chosen_probe=False)

    def problem(window_s: float, noise: float) -> SearchProblem:
        y = 0.2 * fx.rate_c_per_min(temp, t, window_s) + np.random.default_rng(1).normal(0, noise, len(t))
        p = _problem(fine, y, [rate])
        p.rate_window_s = 120.0
        return p

    noisy = problem(120.0, 0.3)
    best, _ = noisy.best_value(rate, ())
    assert not best.value == pytest.approx(120.0, rel=0.05)        # the scan lands elsewhere
    (settled,) = settle_rate_windows(noisy, (best,))
    assert settled.value == pytest.approx(120.0)
    pinned = problem(600.0, 0.01)
    best, _ = pinned.best_value(rate, ())
    (settled,) = settle_rate_windows(pinned, (best,))
    assert settled.value == pytest.approx(600.0, rel=0.03)
    # no declared window (a model without a rate term's filter): nothing is moved
    pinned.rate_window_s = None
    assert settle_rate_windows(pinned, (rate.at(300.0),))[0].value == 300.0


def test_the_exchange_pass_replaces_or_merges_effects_that_stand_in_for_a_missing_one():
    # the truth: a time drift and a lag of the own probe.  A set where a slow lag of another probe stands
    # in for the drift is moved, one effect at a time, to the true one; the true set is left as it is
    from bench.fit.closeloop_search import DBIC_MIN, exchange

    t = np.arange(5.0, 36_000.0, FINE_S)
    t1 = np.interp(t, [0, 5000, 11000, 18000, 25000, 36000], [20, 45, 45, 5, 5, 30])
    t2 = 0.6 * t1 + 8.0 + 4.0 * np.sin(2 * np.pi * t / 14_000.0)
    fine = fx.Inputs(time=t, temps={"t1": t1, "t2": t2},
                     rates={p: fx.rate_c_per_min(v, t, 300.0) for p, v in (("t1", t1), ("t2", t2))},
                     since_on=t - t[0], power_known=False, up=None, input_rate=None)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1", "t2"), channels=("x",), latitude_deg=None)
    fams = {f.label: f for f in fx.families(ctx, fine)}
    lag, drift = fams["thermal_lag(probe=t1)"], fams["time_drift()"]
    y = (0.03 * (fx.first_order_lag(t1, t, 900.0) - t1) + 0.05 * (t - t[0]) / 3600.0
         + np.random.default_rng(5).normal(0, 0.05, len(t)))
    ev = evidence_blocks(t, {"y": y, "one": np.ones_like(t), "u": t1 - 25.0})
    problem = SearchProblem(yb=ev["y"], Xb=np.column_stack([ev["one"], ev["u"]]), fine=fine,
                            declared_signals_b=np.zeros((len(ev["y"]), 0)), families=list(fams.values()),
                            fine_valid=np.isfinite(y))
    stand_in, _ = problem.best_value(fams["thermal_lag(probe=t2, form=absolute)"], (lag.at(900.0),))
    steps: list = []
    moved = exchange(problem, (stand_in, lag.at(900.0)), steps)
    assert {e.family for e in moved} == {drift, lag}
    assert [s["exchanged"] for s in steps] == [[stand_in.label]]
    assert next(e for e in moved if e.family == lag).value == pytest.approx(900.0, rel=0.1)
    truth = problem.refit_params((drift.at(None), lag.at(900.0)), keep_families=True)
    steps = []
    assert exchange(problem, truth, steps) == truth and steps == []
    # two stand-ins sharing the drift's work are merged into it (a merge needs strong evidence)
    second, _ = problem.best_value(fams["thermal_lag(probe=t2)"], (stand_in, lag.at(900.0)))
    steps = []
    merged = exchange(problem, (stand_in, second, lag.at(900.0)), steps)
    assert {e.family for e in merged} == {drift, lag}
    assert any(len(s["exchanged"]) == 2 and s["delta_bic"] > DBIC_MIN for s in steps)


@pytest.mark.parametrize("scale", [1.0, 1.6, 0.6])
def test_an_effect_whose_size_changes_between_the_runs_is_not_the_cause(scale):
    # the training run's structure is an effect the library has; on the validation run the same
    # structure is there at another size, as when a driver no column records (humidity, an internal
    # node) follows temperature differently in each run.  With the effect at 0.6x or 1.6x its training
    # size, adding it still removes 64-86 % of the validation variance above the noise, which the share
    # rule alone took for "partly explained" (measured)
    from bench.fit.closeloop import MAX_SCALE_CHANGE

    train, _ = make_run(TRAIN_PROFILE, {"gradient": 0.3}, seed=21)
    validate, _ = make_run(VALIDATE_PROFILE, {"gradient": 0.3 * scale}, seed=22)
    r = close_loop(train, validate, "static", channels=["x"])["channels"]["x"]
    if scale == 1.0:
        assert r["verdict"] == "explained" and r["effects_added"]
        return
    assert r["verdict"] == "unexplained_structure_remains" and not r["effects_added"]
    assert r["after"]["validation_std100_dph"] == r["before"]["validation_std100_dph"]
    left_out = [e for e in r["effects_not_generalised"] if e["status"].startswith("not the cause")]
    assert left_out and left_out[0]["share_of_excess_variance"] > 0.5
    size = left_out[0]["validation_scale"]
    assert abs(np.log(size)) > np.log(MAX_SCALE_CHANGE) and abs(size - scale) < 0.1
    assert "its training size" in r["findings"]


@pytest.mark.parametrize("needs_both", [False, True])
def test_two_gradients_that_only_hold_a_third_between_them_are_merged_into_it(needs_both):
    # gradients t1-t3 and t2-t3 span t1-t2: when the data need only t1-t2 the pair is a richer form of
    # it, kept only on strong evidence; a corpus three-effect channel ended with the pair (the merge
    # gained 5.7 in BIC, under the 10 a merge needs otherwise; measured)
    from bench.fit.closeloop_search import DBIC_MIN, exchange

    t = np.arange(5.0, 36_000.0, FINE_S)
    t1 = np.interp(t, [0, 5000, 11000, 18000, 25000, 36000], [20, 45, 45, 5, 5, 30])
    t2 = fx.first_order_lag(t1, t, 700.0) + 0.5 * np.sin(2 * np.pi * t / 9_000.0)
    t3 = fx.first_order_lag(t1, t, 2500.0)
    temps = {"t1": t1, "t2": t2, "t3": t3}
    fine = fx.Inputs(time=t, temps=temps, rates={p: fx.rate_c_per_min(v, t, 300.0) for p, v in temps.items()},
                     since_on=t - t[0], power_known=False, up=None, input_rate=None)
    ctx = fx.Context(channel="x", primary_probe="t1", probes=("t1", "t2", "t3"), channels=("x",), latitude_deg=None)
    fams = {f.label: f for f in fx.families(ctx, fine)}
    g12, g13, g23 = (fams[f"gradient(probes={p})"] for p in ("t1-t2", "t1-t3", "t2-t3"))
    y = 0.3 * (t1 - t2) + (0.2 * (t2 - t3) if needs_both else 0.0) + np.random.default_rng(3).normal(0, 0.05, len(t))
    ev = evidence_blocks(t, {"y": y, "one": np.ones_like(t), "u": t1 - 25.0})
    problem = SearchProblem(yb=ev["y"], Xb=np.column_stack([ev["one"], ev["u"]]), fine=fine,
                            declared_signals_b=np.zeros((len(ev["y"]), 0)), families=list(fams.values()),
                            fine_valid=np.isfinite(y))
    pair = (g13.at(None), g23.at(None))
    assert problem.lies_within(g12.at(None), pair) and not problem.lies_within(g13.at(None), (g12.at(None),))
    steps: list = []
    moved = exchange(problem, pair, steps)
    if needs_both:
        assert {e.family for e in moved} == {g13, g23} and steps == []
        return
    assert moved == (g12.at(None),)
    assert steps[0]["exchanged"] == [e.label for e in pair] and 0 < steps[0]["delta_bic"] < DBIC_MIN


@pytest.mark.parametrize("inflated", [True, False])
def test_the_search_goes_on_at_a_floor_that_the_next_addition_lowers(inflated):
    # the stop floor is read from the residual it judges: a slow structure still in it reads as flicker
    # and lifts it.  At that floor the search goes on only when the addition it would make lowers the
    # floor beyond the verdict's tolerance; a floor that stays where it is stops it
    from bench.fit.closeloop_search import AT_FLOOR_RATIO, search

    rng = np.random.default_rng(5)
    t = np.arange(5.0, 40_000.0, FINE_S)
    temp = 20.0 * np.sin(t / 4000.0) + 5.0 * np.sin(t / 1300.0)
    fine = _inputs(t, temp)
    lagged = fx.first_order_lag(temp, t, 900.0) - temp
    lag = fx.Family("thermal_lag", (("probe", "t1"),), lambda x, _v: {"lag900(t1)-t1": lagged})
    drift = fx.Family("time_drift", (), lambda x, _v: {"t_hours": (x.time - x.time[0]) / 3600.0})
    y = 0.2 * lagged + 0.02 * (t - t[0]) / 3600.0 + rng.normal(0, 0.02, len(t))
    problem = _problem(fine, y, [lag, drift])
    high = 10.0          # deg/h: every residual here is "at" it
    # with the lag only, the floor read from the residual is high; with the drift in too, the noise's
    stop_at = (lambda effs: high if len(effs) < 2 else 0.01) if inflated else (lambda effs: high)
    chosen, steps = search(problem, stop_at=stop_at)
    assert steps[0]["added"] and not steps[0].get("floor_inflated")
    if inflated:
        assert sorted(e.kind for e in chosen) == ["thermal_lag", "time_drift"]
        assert steps[1]["floor_inflated"]["stop_std100_dph"] == high
        assert steps[1]["floor_inflated"]["stop_std100_with_it_dph"] * AT_FLOOR_RATIO < high
    else:
        assert len(chosen) == 1 and "stopped" in steps[1]


def test_a_block_the_gyro_was_measured_over_for_a_few_seconds_is_no_evidence():
    # the gyro is switched on 4 s before a 100-s block ends, and its first two readings carry a
    # power-on transient: that block's mean (2 samples) is many times noisier than the others (50).
    # Least squares on block means weighs every block alike, and a warm-up of a few seconds fitted
    # that one block on TRAIN (it did not generalise); nothing is missing from the declared model
    train, _ = make_run(TRAIN_PROFILE, {}, seed=3)
    validate, _ = make_run(VALIDATE_PROFILE, {}, seed=53)
    t = train.time
    y, power = train.columns["gyro_x"].copy(), np.ones(len(t))
    on = int(np.searchsorted(t, t[0] + 12 * 3600 - 4.0))
    y[on - 1800:on], power[on - 1800:on] = np.nan, 0.0
    y[on:on + 2] += 0.6
    train.columns["gyro_x"], train.columns["power"] = y, power
    r = close_loop(train, validate, "static", channels=["x"], bin_c=None)["channels"]["x"]
    assert not [s for s in r["search_steps"] if "added" in s]
    assert r["effects_added"] == [] and r["effects_not_generalised"] == []
    assert r["verdict"] == "no_effect_missing"



def test_the_declared_models_part_in_the_own_probe_is_read_from_its_terms_and_its_training_fit():
    # tc and tc^3 are functions of the own probe alone; dtc and (tc - t4) are not.  The part's shape is
    # the polynomial in (T - 25) through what TRAIN fitted, of its true degree (3, from two terms)
    from bench.fit.closeloop import _declared_design, own_shape

    train, _ = make_run(TRAIN_PROFILE, {}, seed=1)
    validate, _ = make_run(VALIDATE_PROFILE, {}, seed=2)
    _, design, y_tr, _, probe, _ = _declared_design("tc + tc^3 + dtc + (tc-t4)", train, validate, "x", None, {})
    assert [design.names[i] for i in design.own_columns] == ["tc", "tc^3"]
    temp = np.asarray(train[f"temp_{probe}"], dtype=float)
    shape = own_shape(design, y_tr, temp)
    assert len(shape) == 3
    beta = np.linalg.lstsq(design.train[np.isfinite(y_tr)], y_tr[np.isfinite(y_tr)], rcond=None)[0]
    part = design.train[:, list(design.own_columns)] @ beta[list(design.own_columns)]
    u = temp - 25.0
    again = sum(c * u ** j for j, c in enumerate(shape, 1))
    np.testing.assert_allclose(again - again.mean(), part - part.mean(), atol=1e-9 * np.ptp(part))


def test_a_lags_unknown_start_is_a_column_on_the_run_fitted_and_zero_on_any_other():
    # the element soaked at 45 C before logging began: it starts 25 C from its probe's first reading
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 36_000.0, 10.0)
    temp = 20.0 + 15.0 * np.sin(t / 5000.0)
    tau = 1500.0
    a = np.exp(-10.0 / tau)
    element = np.empty_like(temp)
    element[0] = a * 45.0 + (1 - a) * temp[0]
    for i in range(1, len(t)):
        element[i] = a * element[i - 1] + (1 - a) * temp[i]
    y = 0.1 * (element - temp) + rng.normal(0, 0.01, len(t))
    fitted, other = _inputs(t, temp), _inputs(t, temp)
    fitted.start_unknown = True
    start = fx.lag_start(fitted, tau)
    np.testing.assert_allclose(start, np.exp(-t / tau), rtol=1e-12)
    assert not np.any(fx.lag_start(other, tau))
    lag = fx.first_order_lag(temp, t, tau) - temp
    one = np.ones(len(t))
    with_start = np.linalg.lstsq(np.column_stack([one, lag, start]), y, rcond=None)[0]
    without = np.linalg.lstsq(np.column_stack([one, lag]), y, rcond=None)[0]
    assert abs(with_start[1] - 0.1) < 0.002 and abs(without[1] - 0.1) > 0.01
    # the unsettled form is offered for a probe ramping when the run begins, not for one settled there
    ramping = _inputs(t, 20.0 - 0.5 * t / 60.0)
    assert fx.start_rate(ramping, "t1") == pytest.approx(-0.5) and 0.5 >= fx.UNSETTLED_START_C_PER_MIN
    settled = _inputs(t, np.full(len(t), 20.0) + 0.001 * t / 60.0)
    assert abs(fx.start_rate(settled, "t1")) < fx.UNSETTLED_START_C_PER_MIN

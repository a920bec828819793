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


def test_reversal_relay_switches_after_a_reversal_of_one_width():
    x = np.array([0.0, 1.0, 2.9, 3.0, 8.0, 10.0, 8.0, 7.1, 7.0, 2.0, 4.0, 5.0])
    got = fx.reversal_relay_state(x, 3.0, -1.0)
    #              rises 3 above the minimum 0 -> +1; falls 3 below the maximum 10 -> -1; rises 3 above 2 -> +1
    np.testing.assert_array_equal(got, [-1, -1, -1, 1, 1, 1, 1, 1, -1, -1, -1, 1])
    # started on the branch it is driven to, it holds until the first reversal
    np.testing.assert_array_equal(fx.reversal_relay_state(x, 3.0, 1.0)[:8], np.ones(8))


def test_relay_state_is_fixed_by_the_temperature_path_after_the_first_excursion():
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.normal(0, 0.3, 5000))
    w = 2.0
    first = int(np.flatnonzero(np.abs(x - x[0]) >= w)[0])
    up, down = fx.reversal_relay_state(x, w, 1.0), fx.reversal_relay_state(x, w, -1.0)
    np.testing.assert_array_equal(up[first:], down[first:])
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

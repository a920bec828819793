"""A few cases of the third close-the-loop referee (tests/referee3), run through the CLI.

Each case is one gyro unit with two channels, a TRAIN and a VALIDATE run from the referee's own
physics; a case passes when every channel has the right kinds and probes (or a look-alike within
half a noise floor), an honest verdict, and a validation error within 1.15x the oracle's, never
worse than before.  Known misses carry the reason measured when they were added (strict=False: a
better analysis may pass them).
"""
from __future__ import annotations

import numpy as np
import pytest

from tests.referee3 import physics as ph
from tests.referee3.cases import build_case
from tests.referee3.score import score_case

KNOWN_MISSES: dict[tuple[str, int], str] = {}

CASES = [("complete_colder", 1), ("lag", 1), ("unrecorded_humidity", 1), ("relay_hysteresis", 1),
         ("gradual_hysteresis", 2)]


@pytest.mark.timeout(600)
@pytest.mark.parametrize("cls,seed", [
    pytest.param(c, s, marks=pytest.mark.xfail(reason=KNOWN_MISSES[(c, s)], strict=False))
    if (c, s) in KNOWN_MISSES else (c, s) for c, s in CASES])
def test_referee3_case(cls, seed):
    r = score_case(cls, seed)
    assert r.error is None, r.error
    assert r.passed, [(c.channel, c.failures) for c in r.channels]


@pytest.mark.timeout(600)
def test_a_time_drift_is_not_taken_for_a_memory_as_wide_as_the_run():
    # time_drift 8: on its one-excursion training run a Duhem memory of 26.6 C (half the probe's span,
    # the family's limit) once fitted the drift 10 in BIC better, did not generalise (0.195 deg/h on
    # validation against 0.103 without it) and left the channel unexplained at 4.8x the oracle.  A
    # memory that wants to be wider than the run saturates is no candidate: the drift is found, and the
    # error is the oracle's.  The verdict is not asserted here: a second effect chosen on TRAIN that did
    # not generalise (a lag) makes it partly_explained
    r = score_case("time_drift", 8)
    assert r.error is None, r.error
    y = next(c for c in r.channels if c.channel == "y")
    assert not [f for f in y.failures if f.startswith(("kinds", "error"))], y.failures


def test_flicker_allan_floor_is_0664_b():
    """The generator's bias instability has the IEEE 952 Allan floor 0.664 B (within 15 %)."""
    rng = np.random.default_rng(3)
    b = 0.02
    x = ph.flicker(60000, b, rng)
    adev = np.mean([ph.allan_dev(x, m) for m in (30, 100, 300)])
    assert abs(adev / (0.664 * b) - 1) < 0.15, adev


def test_cases_are_seeded_and_quantised():
    a, b = build_case("rate", 3), build_case("rate", 3)
    for k, v in a.train.columns.items():
        np.testing.assert_array_equal(v, b.train.columns[k])
    steps = a.train.columns["temp_t1"] / ph.DS18B20_STEP_C
    np.testing.assert_array_equal(steps, np.round(steps))
    assert a.validate.columns["time_s"][-1] < a.train.columns["time_s"][-1]   # validation is shorter

"""The fifth close-the-loop referee: its generator is deterministic, and a few cases scored through
`bench close-loop` (the CLI and its JSON only, as the referee does).

The full measurement is ``python -m tests.referee5.score --seeds 5 --first-seed 1``.
"""
from __future__ import annotations

import numpy as np
import pytest

from tests.referee5.cases import build_case
from tests.referee5.score import run_case


def test_seeding_is_deterministic():
    a, b = build_case("lag_other", 2), build_case("lag_other", 2)
    assert a.model == b.model and a.channel_probes == b.channel_probes
    assert np.array_equal(a.train["gyro"]["x"], b.train["gyro"]["x"], equal_nan=True)
    assert not np.array_equal(build_case("lag_other", 3).train["gyro"]["x"][:100], a.train["gyro"]["x"][:100])


SCORED = [
    # a play memory that begins the training run as if continuing its first excursion and the
    # validation run elsewhere: 8.3x and 5.1x the oracle with the training start on validation
    pytest.param("hyst_gradual", 4, id="hyst_gradual-4"),
    # a complete channel: a gradient the training run prefers by a hair took 2.6 % off the validation
    # error, within the noise; it was kept and the channel called explained
    pytest.param("complete_steep", 5, id="complete_steep-5"),
    pytest.param("temp_rate", 1, id="temp_rate-1"),
    # y: a warm-up, a gradient t1-t3 and a time drift that partly cancel on the training run: alone or
    # in pairs each fits little (training std100 0.13-0.19 deg/h), all three reach the noise (0.023).
    # Step by step the search took a rate-temperature cross term and a gradient of t1-t2, all of which
    # failed validation: nothing added, unexplained at 0.245 deg/h.  Triples are now fitted at a step
    # when a pair passes and the step's pick leaves the training residual above its floor
    pytest.param("three_effects", 5, id="three_effects-5"),
    # y: taken as a triple, the lag came out on t3 (absolute form) where the truth is the own probe's
    # t1, a tie on TRAIN (SSR 0.1117 against 0.1123); the simpler family of a tie is taken, as the
    # search does for single additions
    pytest.param("three_effects", 3, id="three_effects-3"),
    # y and z: the rate of the own probe named a gradient to t4, which fits it alike; the rate paid a
    # whole parameter for a filter window the run barely pins (BIC 4.9 and 4.8 behind).  The rate through
    # the declared model's own filter, nothing searched but the probe, is now a candidate beside it
    pytest.param("rate", 1, id="rate-1"),
    # x: a heating/cooling relay found on TRAIN (t2, 0.189 C/min against a true 0.19) was turned away:
    # the validation run ends while still cooling, and the 600-s rate held its last full window's slope
    # (-0.16 C/min) over the last 300 s, so the relay missed its last switch and its size on that run
    # came out at 0.76x.  The rate now follows the temperature's curvature to the record's ends
    pytest.param("hyst_relay", 4, id="hyst_relay-4"),
    # z: a time drift on a run that starts at its warmest, so the temperature's running integral is
    # about linear in time: a lag of t2 at twice the record (52,100 s) fitted TRAIN better than the drift
    # (its SSR of 100-s means about 10 % lower, by the noise), did not generalise, and nothing was added:
    # unexplained at 12.6x the oracle.  A lag the data want at the limit the record's length sets is no
    # candidate now
    pytest.param("drift", 101, id="drift-101"),
]


@pytest.mark.parametrize("cls,seed", SCORED)
def test_scored_case(cls, seed):
    r = run_case((cls, seed, ""))
    failures = {c["channel"]: c["reasons"] for c in r["channels"] if not c["passed"]}
    assert r.get("error") is None and r["passed"], failures or r.get("error")

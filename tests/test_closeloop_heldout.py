"""Close-the-loop on held-out cases from an independent generator (tests/heldout), a fast subset.

The full referee score is ``python -m tests.heldout.score --seeds 5``.  Each test generates one case
(a unit, TRAIN and VALIDATE runs with hidden physics on one channel), runs the product's close-the-loop
on that channel and asks for the right effects (kind and probe), an honest verdict and an error within
1.15x of the model with the true effects.  Cases the product currently misses are expected failures
(not strict) with the measured reason.
"""
from __future__ import annotations

import pytest

from tests.heldout.score import score_case

#: (class, seed) -> why the product misses it today (measured with tests.heldout.score)
KNOWN_MISSES: dict[tuple[str, int], str] = {
    ("gradual_hysteresis", 1): "explained, after 1.01x the oracle, but the memory named on t1 for the true t2 "
                               "(Duhem, reversed start): the training run barely tells the two probes apart "
                               "(BIC margin 2.3 at the step, below the ambiguity bar 6)",
}

SUBSET = [
    ("complete_colder", 1),
    ("complete_short", 1),
    ("complete_inside", 3),
    ("lag_any_probe", 1),
    ("gradient", 1),
    ("warmup", 1),
    ("two_effects", 2),
    ("relay_hysteresis", 1),
    ("gradual_hysteresis", 1),
    ("unexplained_sinusoid", 1),
    ("unexplained_step", 1),
    # a bias step no column records: a warm-up of 9120 s, a Duhem memory and a gradient fitted it
    # together on TRAIN (taken as a triple, the residual still above its floor) and the warm-up was
    # kept on VALIDATE (partly explained); three effects at once are taken only when they bring the
    # training residual to its floor
    ("unexplained_step", 43),
]


def _param(cls: str, seed: int):
    why = KNOWN_MISSES.get((cls, seed))
    marks = [pytest.mark.xfail(reason=why, strict=False)] if why else []
    return pytest.param(cls, seed, id=f"{cls}-seed{seed}", marks=marks)


@pytest.mark.parametrize("cls,seed", [_param(c, s) for c, s in SUBSET])
def test_heldout_case(cls, seed):
    r = score_case(cls, seed)
    assert r["passed"], (f"{r['case']} channel {r['channel']}: truth {r['truth'] or 'none'}, product "
                         f"{r.get('verdict')} {r.get('added')}: " + " | ".join(r["reasons"]))

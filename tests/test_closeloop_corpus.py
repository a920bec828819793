"""The referee corpus (issue 12 point 8): one test per case class, over a few seeds; each asserts
that the referee (tests/corpus/referee.py) passes the product's close-the-loop on that case.  The
table over more seeds comes from ``python -m tests.corpus.score``."""
from __future__ import annotations

import pytest

from tests.corpus.cases import CLASSES, make_case
from tests.corpus.referee import score_case

SEEDS = (1, 2, 3)

# Known misses of the current close-the-loop, measured on this corpus (seeds 1-3); each is an expected
# failure with its reason, every other case is a real test.  When the analysis improves, a known miss
# that passes shows up as XPASS: remove it from this table.
KNOWN_MISSES = {
    "effect_validation_colder": {1: "y: a gradient t1-t2 taken for a lag of t1 (the training run cannot tell "
                                    "them apart: delta-BIC margin 2, now named in ambiguous_with); "
                                    "partly_explained"},
    "three_effects": {2: "z: after 1.03x the oracle, explained, but the gradient named t2-t3 for the true "
                         "t1-t2 and a rate of t4 kept beside the memory and the warm-up (since a training "
                         "block measured over less than half its samples is no evidence; it had passed, "
                         "and failed once before on CI)",
                      3: "z: explained at 1.34x the oracle, the rate of t4 and (T-25) dT/dt of t1 named as "
                         "(T - T0) dT/dt of t3 (window 743 s) and of t2 (388 s): the cross term's own dT/dt "
                         "column with a long window stands in for the lagging t4's rate at the first step "
                         "(before (T - T0) dT/dt it had passed, the rate named as the look-alike gradient "
                         "t1-t4)"},
}


def _params():
    for case_class in CLASSES:
        for seed in SEEDS:
            reason = KNOWN_MISSES.get(case_class, {}).get(seed)
            marks = [pytest.mark.xfail(strict=False, reason=f"known miss: {reason}")] if reason else []
            yield pytest.param(case_class, seed, marks=marks, id=f"{case_class}-{seed}")


@pytest.mark.parametrize("case_class,seed", list(_params()))
def test_corpus_case_passes_the_referee(case_class, seed):
    scores = score_case(make_case(case_class, seed))
    failures = [f"{s.channel}: " + "; ".join(s.reasons) + f" | {s.numbers}" for s in scores if not s.passed]
    assert not failures, "\n".join(failures)

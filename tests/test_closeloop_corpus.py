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
    "three_effects": {3: "z: explained at 1.02x the oracle, the rate of t4 (beside the warm-up and the "
                         "T dT/dt of t1) named as the gradient t3-t4: on the recorded probes the training "
                         "run puts the rate 4.6 in BIC behind (named in ambiguous_with); on the true nodes "
                         "the gradient imitates the rate within 0.54 noise floors, just outside the 0.5 "
                         "that makes a look-alike"},
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

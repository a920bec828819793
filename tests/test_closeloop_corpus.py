"""The referee corpus (issue 12 point 8): one test per case class, over a few seeds; each asserts
that the referee (tests/corpus/referee.py) passes the product's close-the-loop on that case.  The
table over more seeds comes from ``python -m tests.corpus.score``."""
from __future__ import annotations

import pytest

from tests.corpus.cases import CLASSES, make_case
from tests.corpus.referee import score_case

SEEDS = (1, 2, 3)

# The one switch.  While the close-the-loop rewrite is pending, the (class, seeds) that the algorithm
# of the first release fails (measured with ``python -m tests.corpus.score --seeds 3``) are expected
# failures; every other case is a real test.  Set to False once the rewrite passes the corpus.
CLOSE_LOOP_REWRITE_PENDING = True
FAILING_BEFORE_REWRITE = {
    "complete_validation_colder": (1, 2, 3),
    "complete_validation_hotter": (1, 2, 3),
    "complete_strong_flicker": (1, 2, 3),
    "effect_off_own_probe_thermal_lag": (2, 3),
    "effect_off_own_probe_rate_squared": (3,),
    "effect_off_own_probe_temp_rate_cross": (3,),
    "effect_off_own_probe_hysteresis": (1, 2, 3),
    "effect_off_own_probe_g_sensitivity": (3,),
    "effect_off_own_probe_scale_factor_temperature": (2, 3),
    "effect_validation_colder": (1, 2, 3),
    "effect_with_flicker": (2,),
    "two_effects": (1, 2, 3),
    "three_effects": (1, 2, 3),
    "gradual_hysteresis": (1, 2, 3),
    "long_time_constant": (1, 2, 3),
}


def _params():
    for case_class in CLASSES:
        for seed in SEEDS:
            pending = CLOSE_LOOP_REWRITE_PENDING and seed in FAILING_BEFORE_REWRITE.get(case_class, ())
            marks = [pytest.mark.xfail(strict=False, reason="close-loop rewrite pending")] if pending else []
            yield pytest.param(case_class, seed, marks=marks, id=f"{case_class}-{seed}")


@pytest.mark.parametrize("case_class,seed", list(_params()))
def test_corpus_case_passes_the_referee(case_class, seed):
    scores = score_case(make_case(case_class, seed))
    failures = [f"{s.channel}: " + "; ".join(s.reasons) + f" | {s.numbers}" for s in scores if not s.passed]
    assert not failures, "\n".join(failures)

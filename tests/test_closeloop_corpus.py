"""The referee corpus (issue 12 point 8): one test per case class, over a few seeds; each asserts
that the referee (tests/corpus/referee.py) passes the product's close-the-loop on that case.  The
full table over more seeds comes from ``python -m tests.corpus.score``."""
from __future__ import annotations

import pytest

from tests.corpus.cases import CLASSES, make_case
from tests.corpus.referee import score_case

# The one switch: while the close-the-loop rewrite is pending, the cases it fails are expected failures.
CLOSE_LOOP_REWRITE_PENDING = True
SEEDS = (1, 2)

pytestmark = ([pytest.mark.xfail(strict=False, reason="close-loop rewrite pending")]
              if CLOSE_LOOP_REWRITE_PENDING else [])


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("case_class", list(CLASSES))
def test_corpus_case_passes_the_referee(case_class, seed):
    scores = score_case(make_case(case_class, seed))
    failures = [f"{s.channel}: " + "; ".join(s.reasons) + f" | {s.numbers}" for s in scores if not s.passed]
    assert not failures, "\n".join(failures)

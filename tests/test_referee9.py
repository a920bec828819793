"""Referee 9: an outside lab's generator (tests/referee9).  Fast cases only; the full table comes from
`python -m tests.referee9.score --seeds 3`."""
import numpy as np
import pytest

from tests.referee9 import cases as C
from tests.referee9 import score as S


def test_generator_is_deterministic():
    for cls in ("irregular_logging", "multipos_gsens"):
        a, b = C.build(cls, 2), C.build(cls, 2)
        assert a.probes == b.probes and a.model == b.model
        for ra, rb in ((a.train, b.train), (a.validate, b.validate)):
            assert np.array_equal(ra.t, rb.t)
            for ch in C.CHANNELS:
                assert np.array_equal(ra.gyro[ch], rb.gyro[ch], equal_nan=True)
            for p in ra.temps:
                assert np.array_equal(ra.temps[p], rb.temps[p], equal_nan=True)
        assert [e["scale_dph"] for ch in C.CHANNELS for e in a.truth[ch]["effects"]] == \
               [e["scale_dph"] for ch in C.CHANNELS for e in b.truth[ch]["effects"]]
    c3 = C.build("irregular_logging", 3)
    assert not np.array_equal(c3.train.gyro["x"], C.build("irregular_logging", 2).train.gyro["x"])


# a complete named `dynamic` model under strong flicker, a multi-position test with Earth rate and
# g-sensitivity, a supply dependence no column records, jittered 1-s / 5-s-averaged logging
@pytest.mark.parametrize("cls,seed", [("dynamic_complete_flicker", 1), ("multipos_gsens", 1),
                                      ("unrecorded_supply", 3),
                                      ("irregular_logging", 1)])
def test_referee9_case(cls, seed):
    r = S.score_case(cls, seed)
    assert r.get("error") is None, r.get("error")
    bad = [f"{c['ch']}: {'; '.join(c['reasons'])}" for c in r["chans"] if not c["ok"]]
    assert not bad, bad

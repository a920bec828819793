"""The eighth close-the-loop referee: an outside lab's generator (a seven-node network stepped exactly
with a simulated history before the first logged row, probe names shuffled per unit, flicker as a sum of
Gauss-Markov terms), written from the CLI's contract.  Its generator is deterministic from (class,
seed); a case is scored through `bench close-loop` (the CLI and its JSON only).

The full measurement is ``python -m tests.referee8.score --seeds 3 --first-seed 1``.
"""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from tests.referee8 import cases as C


def _digest(case):
    h = hashlib.sha256()
    for run in (case.train, case.validate):
        h.update(run.t.tobytes())
        for ch in C.CHANNELS:
            h.update(np.nan_to_num(run.gyro[ch]).tobytes())
        for p in case.probes:
            h.update(run.temps[p].tobytes())
    h.update(repr(sorted(case.channel_probes.items())).encode())
    h.update(case.formula.encode())
    return h.hexdigest()


def test_same_class_and_seed_give_the_same_case():
    for cls in ("lag_own", "unrecorded_supply"):
        a, b = C.build(cls, 2), C.build(cls, 2)
        assert _digest(a) == _digest(b)
        assert {ch: [(e["kind"], e["probes"]) for e in a.truth[ch]["effects"]] for ch in C.CHANNELS} == \
               {ch: [(e["kind"], e["probes"]) for e in b.truth[ch]["effects"]] for ch in C.CHANNELS}


def test_other_seed_or_class_differs_and_truth_is_declared():
    a, b = C.build("gradient_base", 1), C.build("gradient_base", 2)
    assert _digest(a) != _digest(b)
    kinds = [e["kind"] for ch in C.CHANNELS for e in a.truth[ch]["effects"]]
    assert kinds == ["gradient"]
    assert all(a.truth[ch]["verdicts"] for ch in C.CHANNELS)
    assert set(a.channel_probes.values()) <= set(a.probes)


@pytest.mark.parametrize("cls,seed", [
    # the unit soaked hot before logging began: the lag's element starts 10-15 C behind its probe on
    # TRAIN; without that start offset as a column of the lag a warm-up stood in for it on TRAIN and
    # did not generalise, and the lag was left at 1.20x the oracle, partly explained
    ("nonequilibrium_start", 3),
    # three slow sines and a mode hop of the supply, which no column records: unexplained
    ("unrecorded_supply", 1),
    # nothing missing under four times the usual flicker: nothing added
    ("complete_flicker", 1),
])
def test_cases_pass_the_eighth_referee(cls, seed):
    from tests.referee8.score import score_case

    got = score_case(cls, seed)
    assert "error" not in got, got.get("error")
    failures = {c["ch"]: c["reasons"] for c in got["chans"] if not c["ok"]}
    assert not failures, failures

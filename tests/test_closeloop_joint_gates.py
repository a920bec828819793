"""Each effect of a joint move (a pair or a triple taken in one step) passes the GLS F test under the
noise model of the whole move's residual, the others in, at a single addition's level.  On a held-out
draw a time drift that a HAC test with its few lags passed beside a strong rate was the training run's
flicker: it did not generalise, and kept a channel whose right rate sat at the oracle's error from
being called explained."""
from __future__ import annotations


def _kinds(ch: dict) -> list[str]:
    return [e["kind"] for e in ch["effects_added"]]


def test_no_time_drift_is_taken_beside_a_rate_for_the_training_runs_flicker():
    from tests.heldout.cases import make_case
    from tests.heldout.score import run_product

    ch = run_product(make_case("effect_validation_colder", 52))       # the truth: a rate of t3
    assert _kinds(ch) == ["rate"], ch["findings"]
    assert not ch["effects_not_generalised"], ch["findings"]
    assert ch["verdict"] == "explained", ch["findings"]
    pairs = [s["evidence"] for s in ch["search_steps"] if s.get("evidence", {}).get("pair")]
    assert all(max(ev["each_gls_f_p"]) < 1e-3 for ev in pairs), pairs


def test_a_true_time_drift_beside_a_memory_is_still_taken():
    # the fourth referee's two effects, seed 12: y holds a play memory of t2 and a time drift, x and z
    # nothing; each member's test is made with its own columns last (the F test's nesting), so the
    # memory's p is its own, and the drift stands beside it
    from tests.referee4.score import score_case

    result = score_case("two_effects", 12)
    y = next(c for c in result["channels"] if c["channel"] == "y")
    assert sorted(y["added"]) == sorted(y["expected"]), y
    assert result["ok"], [c["failures"] for c in result["channels"]]

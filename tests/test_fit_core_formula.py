"""Formula parser and design-matrix builder."""
from __future__ import annotations

import numpy as np
import pytest

from bench.fit.base import Dataset
from bench.fit.formula import FormulaError, compile_formula, node_text, parse_formula
from bench.fit.prep import rate_c_per_min


def _ds(n=2000):
    t = np.arange(n, dtype=float)
    return Dataset({"time_s": t, "gyro_x": np.zeros(n), "temp_t1": 20 + 0.01 * t, "temp_t3": 18 + 0.02 * t,
                    "lag_t1_600": 19 + 0.01 * t, "chamber_pv": 25 + 0.0 * t})


def test_issue_example_builds_the_right_columns():
    ds = _ds()
    f = compile_formula("t1 + t1^2 + t1^3 + dt1 + (t1-t3) + t1*dt1", ds.columns, rate_window_s=60.0)
    assert f.names == ["intercept", "t1", "t1^2", "t1^3", "dt1", "(t1-t3)", "t1*dt1"]
    x, flagged = f.design(ds)
    t1, t3 = ds["temp_t1"], ds["temp_t3"]
    r1 = rate_c_per_min(ds.time, t1, 60.0)
    np.testing.assert_allclose(r1[100:-100], 0.6)       # 0.01 C/s = 0.6 C/min
    expected = np.column_stack([np.ones(len(ds)), t1, t1 ** 2, t1 ** 3, r1, t1 - t3, t1 * r1])
    np.testing.assert_allclose(x, expected)
    assert not flagged.any()
    assert f.units["t1^2"] == "deg/h/C^2" and f.units["dt1"] == "deg/h/(C/min)"
    assert f.units["t1*dt1"] == "deg/h/(C*C/min)" and f.units["intercept"] == "deg/h"


def test_atoms_resolve_to_any_column_and_centring_constants_work():
    ds = _ds()
    f = compile_formula("lag_t1_600 + (t1-25)^2 + chamber_pv*t3 + 1", ds.columns)
    assert f.names == ["intercept", "lag_t1_600", "(t1-25)^2", "chamber_pv*t3"]
    x, _ = f.design(ds)
    np.testing.assert_allclose(x[:, 1], ds["lag_t1_600"])
    np.testing.assert_allclose(x[:, 2], (ds["temp_t1"] - 25) ** 2)
    np.testing.assert_allclose(x[:, 3], ds["chamber_pv"] * ds["temp_t3"])


def test_clipping_flags_samples_outside_the_range():
    ds = _ds()
    f = compile_formula("t1 + dt1", ds.columns)
    x, flagged = f.design(ds, clip={"temp:temp_t1": [20.0, 30.0]})
    assert flagged.sum() == int(np.sum(ds["temp_t1"] > 30.0))
    assert x[:, 1].max() == 30.0


@pytest.mark.parametrize("text, pos, words", [
    ("t1 + * t2", 6, "expected a signal"),
    ("t1 - t3", 4, "gradient as (a-b)"),
    ("t1 + (t1-t3", 12, "missing ')'"),
    ("t1^0", 4, "exponent"),
    ("t1^1.5", 4, "exponent"),
    ("t1 + t9", 6, "unknown signal 't9'"),
    ("t1 + 2", 6, "constant term"),
    ("t1 + t1", 6, "appears twice"),
    ("t1 $ t3", 4, "unexpected character '$'"),
    ("", 1, "empty"),
    ("t1 +", 5, "ends"),
    ("t1 t3", 4, "expected '+' or end"),
])
def test_bad_formulas_report_the_position(text, pos, words):
    with pytest.raises(FormulaError) as err:
        compile_formula(text, _ds().columns)
    assert err.value.position == pos, str(err.value)
    assert words in str(err.value)
    assert f"position {pos}" in str(err.value)


def test_canonical_text_round_trips():
    for text in ("t1", "(t1-25)^3", "((t1-25)*dt1)^2", "t1*dt1*t3", "(t1-t3+t4)", "(t1-(t3-t4))"):
        (node,) = parse_formula(text)
        assert node_text(parse_formula(node_text(node))[0]) == node_text(node)
    (node,) = parse_formula("(t1 - 25.5) ^ 2")
    assert node_text(node) == "(t1-25.5)^2"

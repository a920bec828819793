"""The coefficients read path on SQLite and PostgreSQL: the latest accepted version per model, a given
version accepted or not, the ETag following the fit rows, stored NaN read back, clear errors."""
from __future__ import annotations

import math

import pytest

from api.coefficients import NoCoefficients, coefficient_rows, coefficients_etag, load_coefficients
from bench.storage.models import Fit, Gyro


def _fit(version: int, channel: str, accepted: bool, a1: float, r2: float | None) -> Fit:
    return Fit(gyro_id="G-C", run_ids=[version], model="static", channel=channel, version=version,
               coefficients={"A0": 1.0, "A1": a1}, accepted=accepted,
               result={"units": {"A1": "deg/h/C"}, "validity": {"t1": [-40.0, 85.0]},
                       "definition": {"probe": "t1", "formula": "t1"}, "stats": {"r2": r2}})


def test_coefficients_follow_the_accepted_rows_and_the_etag_changes_with_them(db):
    r2 = math.nan if db.dialect == "sqlite" else None      # SQLite keeps Python's NaN token (orjson refuses it)
    with db.session() as s:
        s.add(Gyro(gyro_id="G-C", type="RLG", notes=""))
        s.flush()
        s.add_all([_fit(1, ch, True, 0.1, r2) for ch in "xyz"] + [_fit(2, ch, False, 0.2, r2) for ch in "xyz"])
    doc = load_coefficients(db, "G-C")
    (m,) = doc["models"]
    assert (m["version"], m["accepted"], m["run_ids"]) == (1, True, [1])
    assert set(m["channels"]) == {"x", "y", "z"}
    assert m["channels"]["y"] == {"coefficients": {"A0": 1.0, "A1": 0.1}, "units": {"A1": "deg/h/C"},
                                  "probe": "t1", "validity": {"t1": [-40.0, 85.0]},
                                  "definition": {"probe": "t1", "formula": "t1"}}
    v2 = load_coefficients(db, "G-C", model="static", version=2)["models"][0]
    assert v2["accepted"] is False and v2["channels"]["x"]["coefficients"]["A1"] == 0.2
    before = coefficients_etag(coefficient_rows(db, "G-C"))
    with db.session() as s:
        for row in s.query(Fit).filter(Fit.gyro_id == "G-C"):
            row.accepted = row.version == 2
    assert coefficients_etag(coefficient_rows(db, "G-C")) != before
    assert load_coefficients(db, "G-C")["models"][0]["version"] == 2
    with pytest.raises(NoCoefficients, match="no gyro 'NOPE'") as err:
        load_coefficients(db, "NOPE")
    assert not err.value.gyro_known
    with pytest.raises(NoCoefficients, match="has no hrg version 1") as err:
        load_coefficients(db, "G-C", model="hrg", version=1)
    assert err.value.gyro_known

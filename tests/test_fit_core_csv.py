"""Measured-data CSV v1: reading, refusing bad files (line + column), exact round trip, speed."""
from __future__ import annotations


import numpy as np
import pytest

from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.csvio import format_csv, parse_csv_text, read_csv, write_csv

GOOD = """# gyro_id: KVH-0042
# gyro_type: kvh_a
# latitude_deg: 45.75
# sample_period_s: 1.0
# first free note
# notes: second note
time_s,gyro_x,gyro_y,temp_t1,temp_t2,freq_x,orientation,power,chamber_pv,chamber_sp,table_rate_dps
0.0,10.5,-3.25,25.0625,24.9375,4321.5,NUE,1,25.0,25.0,0.0
1.0,10.6,,25.125,24.9375,4321.6,ENU,1,25.1,25.0,0.0
2.0,10.4,-3.5,,25.0,,,0,,,
"""


def test_reads_metadata_columns_and_missing_values():
    ds = parse_csv_text(GOOD)
    assert ds.meta["gyro_id"] == "KVH-0042"
    assert ds.meta["latitude_deg"] == "45.75"
    assert ds.meta["notes"] == "first free note\nsecond note"
    assert len(ds) == 3
    assert ds.gyro_channels() == ["x", "y"]
    assert ds.temp_names() == ["t1", "t2"]
    assert np.isnan(ds["gyro_y"][1]) and ds["gyro_y"][2] == -3.5
    assert np.isnan(ds["temp_t1"][2])
    assert list(ds["orientation"]) == ["NUE", "ENU", ""]
    assert ds["power"].tolist() == [1.0, 1.0, 0.0]


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    n = 500
    ds = Dataset({"time_s": np.cumsum(rng.uniform(0.5, 1.5, n)),
                  "gyro_x": rng.normal(0, 1e3, n) * rng.uniform(0, 1, n) ** 7,
                  "gyro_z": np.where(rng.uniform(size=n) < 0.1, np.nan, rng.normal(size=n) / 3),
                  "temp_t1": rng.uniform(-40, 80, n), "freq_x": 4321.0 + rng.normal(size=n) * 1e-7,
                  "orientation": np.array(rng.choice(["ESD", "USE", "WSU", "DSW", ""], n), dtype=str),
                  "power": rng.integers(0, 2, n).astype(float)},
                 {"gyro_id": "G1", "latitude_deg": "45.75", "notes": "a\nb: c"})
    path = tmp_path / "run.csv"
    write_csv(ds, path)
    back = read_csv(path)
    assert back.meta == ds.meta
    assert list(back.columns) == list(ds.columns)
    for k, v in ds.columns.items():
        if k == "orientation":
            assert back[k].tolist() == v.tolist()
        else:
            np.testing.assert_array_equal(back[k], v)   # bit-exact, NaN == NaN
    assert format_csv(back) == path.read_text()


@pytest.mark.parametrize("text, line, column, words", [
    ("time_s,gyro_x,temp_t1\n0,1,2\n1,x1,3\n", 3, "gyro_x", "not a number"),
    ("time_s,gyro_x,temp_t1\n0,1,2\n1,2\n", 3, None, "2 fields"),
    ("time_s,gyro_x,temp_t1,accel_x\n0,1,2,3\n", 1, "accel_x", "unknown column"),
    ("time_s,gyro_x,temp_t1\n0,1,2\n0,1,2\n", 3, "time_s", "strictly increasing"),
    ("time_s,gyro_x,temp_t1\n0,1,2\n,1,2\n", 3, "time_s", "empty"),
    ("# a: 1\ntime_s,gyro_x,temp_t1,orientation\n0,1,2,NUE\n1,1,2,NEU\n", 4, "orientation", "left-handed"),
    ("time_s,gyro_x,temp_t1,orientation\n0,1,2,NNU\n", 2, "orientation", "different"),
    ("time_s,gyro_x,temp_t1,power\n0,1,2,2\n", 2, "power", "0 or 1"),
    ("time_s,gyro_x,temp_t1\n0,1,inf\n", 2, "temp_t1", "finite"),
    ("time_s,gyro_x,temp_t1\n0,1,2\n1,nan,2\n", 3, "gyro_x", "finite"),
    ("time_s,temp_t1\n0,1\n", 1, None, "gyro_"),
    ("time_s,gyro_x\n0,1\n", 1, None, "temp_"),
    ("gyro_x,temp_t1\n0,1\n", 1, None, "time_s"),
    ("# latitude_deg: north\ntime_s,gyro_x,temp_t1\n0,1,2\n", 1, None, "latitude_deg"),
    ("time_s,gyro_x,gyro_x,temp_t1\n0,1,2,3\n", 1, "gyro_x", "duplicate"),
])
def test_bad_files_name_line_and_column(text, line, column, words):
    with pytest.raises(DataFormatError) as err:
        parse_csv_text(text, source="bad.csv")
    assert err.value.line == line
    assert err.value.column == column
    assert words in str(err.value)
    assert f"line {line}" in str(err.value) and "bad.csv" in str(err.value)


def test_bad_file_is_not_half_written(tmp_path):
    path = tmp_path / "out.csv"
    path.write_text("old content\n")
    ds = Dataset({"time_s": np.array([0.0, 0.0]), "gyro_x": np.zeros(2), "temp_t1": np.zeros(2)})
    with pytest.raises(DataFormatError):
        write_csv(ds, path)
    assert path.read_text() == "old content\n"
    assert list(tmp_path.iterdir()) == [path]


def test_a_day_of_one_second_data_round_trips(tmp_path):
    """A day of 1-s data round-trips exactly (the read speed is measured in tests/perf/csvio.py)."""
    n = 86400
    rng = np.random.default_rng(0)
    ds = Dataset({"time_s": np.arange(n, dtype=float), "gyro_x": rng.normal(size=n), "gyro_y": rng.normal(size=n),
                  "gyro_z": rng.normal(size=n), "temp_t1": np.round(rng.normal(25, 5, n) / 0.0625) * 0.0625,
                  "temp_t2": np.round(rng.normal(25, 5, n) / 0.0625) * 0.0625, "chamber_pv": rng.normal(25, 5, n),
                  "orientation": np.full(n, "NUE")}, {"gyro_id": "perf"})
    path = tmp_path / "day.csv"
    write_csv(ds, path)
    back = read_csv(path)
    assert len(back) == n
    for name, col in ds.columns.items():
        assert np.array_equal(back[name], col), name


def test_fast_and_slow_parsers_agree(monkeypatch):
    from bench.fit import csvio

    fast = parse_csv_text(GOOD + "3.0, 1.5 ,-2,25,25,,WSU,1,1e-3,.5,-0.0\n\n")
    monkeypatch.setattr(csvio, "_fast_columns", lambda body, header: None)
    slow = parse_csv_text(GOOD + "3.0, 1.5 ,-2,25,25,,WSU,1,1e-3,.5,-0.0\n\n")
    assert fast.meta == slow.meta and list(fast.columns) == list(slow.columns)
    for k in fast.columns:
        if k == "orientation":
            assert fast[k].tolist() == slow[k].tolist()
        else:
            np.testing.assert_array_equal(fast[k], slow[k])

"""Export columns: 1-s and per-frame alignment of gyro, probes, telemetry and segment labels."""
from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.interfaces import AxisState, ChamberStatus, ProbeReading
from bench.storage import FrameWriter, export_columns, export_parquet, queries
from tests.test_storage_support import db, make_frames, run_id  # noqa: F401 - fixtures

T0 = 1_700_000_000.0


def _record(db, run_id):
    frames = make_frames(4000, t0=T0, rate_hz=200.0, seed=11)            # 20 s at 200 Hz
    with FrameWriter(db, run_id, autostart=False) as w:
        w.add_many(frames)
        for k in range(0, 20, 2):                                        # probes every 2 s, t2 faulty at 6 s
            w.add_probe_readings(T0 + k + 0.1, [
                ProbeReading("t1", "0000000000a1", 20.0 + k),
                ProbeReading("t2", "0000000000a2", None if k == 6 else 30.0 + k, "crc" if k == 6 else None)])
        for k in range(20):
            w.add_chamber(T0 + k, ChamberStatus(pv_c=-10.0 + k, setpoint_c=-5.0, ramp_setpoint_c=None, mode=1,
                                                alarm=0, input_error=0, power_on=True))
            w.add_psu(T0 + k, 28.0, 0.5 + 0.01 * k, True)
        w.add_turntable(T0, {1: AxisState(90.0, 0.0), 2: AxisState(0.0, 0.0)})
        w.add_segment("soak", T0, T0 + 5.0, temperature_c=-10.0)
        w.add_segment("record", T0 + 5.0, T0 + 12.0, temperature_c=-10.0, orientation="ENU", repetition=1)
    with db.session() as s:
        seg = queries.open_segment(s, run_id, "record", T0 + 12.0, orientation="UEN", temperature_c=-10.0)
        assert seg.t_end is None
    return frames


def test_per_second_columns(db, run_id):
    frames = _record(db, run_id)
    cols = export_columns(db, run_id)
    n = len(cols["time_s"])
    assert n == 20 and all(len(v) == n for v in cols.values())
    assert np.array_equal(cols["n_frames"], np.full(20, 200))
    g = np.array([f.gyro for f in frames])
    assert np.allclose(cols["gyro_x"], g[:, 0].reshape(20, 200).mean(axis=1) * 3600.0, atol=1e-9)
    assert np.allclose(cols["time_s"], np.arange(20) + 0.4975 + 1e-4, atol=1e-4)   # mean frame time + jitter
    # probe readings (every 2 s at 2j+0.1, value rising 1 C/s) interpolated at each second's time;
    # after the last reading (18.1 s) its value is held for up to max_age_s
    k = np.arange(20)
    t_sec = cols["bench_time_s"] - T0
    expected_t1 = np.minimum(20.0 + (t_sec - 0.1), 38.0)
    assert np.allclose(cols["temp_t1"], expected_t1, atol=1e-6)
    # the faulty t2 reading at 6.1 s is skipped: 4.1 -> 8.1 s interpolated across it, same straight line
    assert np.allclose(cols["temp_t2"], np.minimum(30.0 + (t_sec - 0.1), 48.0), atol=1e-6)
    assert np.allclose(cols["chamber_pv"], -10.0 + k) and np.all(cols["chamber_sp"] == -5.0)
    assert np.allclose(cols["power_w"], 28.0 * (0.5 + 0.01 * k))
    assert np.all(np.isnan(cols["axis1_pos"][k > 0.5 + 30]))   # older than max_age -> NaN
    assert cols["axis1_pos"][0] == 90.0
    assert list(cols["segment_kind"][[0, 6, 15]]) == ["soak", "record", "record"]
    assert list(cols["orientation"][[0, 6, 15]]) == ["", "ENU", "UEN"]
    assert cols["repetition"][6] == 1 and cols["temp_point_c"][0] == -10.0


def test_per_frame_columns_and_rad_units(db, run_id):
    frames = _record(db, run_id)
    cols = export_columns(db, run_id, resolution="frame", units="rad/s", t_from=T0 + 3, t_to=T0 + 4)
    idx = cols["frame_index"]
    assert np.array_equal(idx, np.arange(idx[0], idx[0] + len(idx))) and len(idx) in (200, 201)
    g = np.array([frames[i].gyro for i in idx])
    assert np.allclose(cols["gyro_z"], g[:, 2] * 180.0 / math.pi * 3600.0)
    assert np.allclose(cols["temp_t1"], 20.0 + (cols["bench_time_s"] - T0 - 0.1), atol=1e-6)


def test_parquet_export_round_trips(db, run_id, tmp_path):
    _record(db, run_id)
    path = export_parquet(db, run_id, tmp_path / "run.parquet")
    table = pq.read_table(path)
    cols = export_columns(db, run_id)
    assert table.num_rows == 20 and set(table.column_names) == set(cols)
    assert np.allclose(table.column("gyro_y").to_numpy(), cols["gyro_y"])
    assert table.column("orientation").to_pylist()[15] == "UEN"
    assert table.schema.metadata[b"run_id"] == str(run_id).encode()


def test_unknown_units_refused(db, run_id):
    with pytest.raises(Exception, match="unit 'furlong/s' unknown"):
        export_columns(db, run_id, units="furlong/s")

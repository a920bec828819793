"""Bad-input drills on ``bench import`` and the measured-data CSV (issue "bad input never half-writes"):
each case gives a one-line error naming what and where, and leaves nothing behind (no run, no rows)."""
from __future__ import annotations

import numpy as np
import pytest
from sqlalchemy import func, select
from typer.testing import CliRunner

from bench.cli import app
from bench.commands.importing import import_csv
from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.catalog import fit_model
from bench.fit.csvio import CsvStream, read_csv, write_csv
from bench.storage import open_database
from bench.storage.export import run_dataset
from bench.storage.models import FrameChunk, ProbeReadingRow, Run, Segment, Telemetry

runner = CliRunner()



def _nothing_stored(db) -> None:
    with db.session() as s:
        for table in (Run, FrameChunk, ProbeReadingRow, Telemetry, Segment):
            assert s.scalar(select(func.count()).select_from(table)) == 0, table.__tablename__


def _csv(path, n=300, *, meta="# latitude_deg: 45.75\n", header="time_s,gyro_x,gyro_y,gyro_z,temp_t1,temp_t2",
         row=None, bom=False):
    t = np.arange(n, dtype=float)
    lines = [meta + header] if meta else [header]
    for i in range(n):
        T = 20.0 + 10.0 * np.sin(i / 50.0)
        values = row(i, T) if row else [t[i], 3.0 + 0.1 * T, -2.0, 10.0 + 0.01 * T, T, T - 0.2]
        lines.append(",".join(repr(float(v)) if not isinstance(v, str) else v for v in values))
    text = "\n".join(lines) + "\n"
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


def _refused(db, path, match: str) -> DataFormatError:
    with pytest.raises(DataFormatError, match=match) as info:
        import_csv(db, path, "G1")
    assert "\n" not in str(info.value)
    _nothing_stored(db)
    return info.value


def test_gyro_rate_beyond_the_frame_format_and_the_gyro_range(db, tmp_path):
    bad = lambda i, T: [i, 3.0, -2.0, 1e308 if i == 117 else 10.0, T, T]            # noqa: E731
    err = _refused(db, _csv(tmp_path / "a.csv", row=bad), r"data row 118\), column 'gyro_z': 1e\+308 deg/h is outside")
    assert "range_dps" in str(err)
    # within float32 but beyond the gyro's +-490 deg/s
    fast = lambda i, T: [i, 600.0 * 3600.0 if i == 5 else 3.0, -2.0, 10.0, T, T]  # noqa: E731
    _refused(db, _csv(tmp_path / "b.csv", row=fast), r"data row 6\), column 'gyro_x'")


def test_implausible_temperature_and_frequency(db, tmp_path):
    hot = lambda i, T: [i, 3.0, -2.0, 10.0, 1e300 if i == 40 else T, T]               # noqa: E731
    _refused(db, _csv(tmp_path / "a.csv", row=hot), r"line 43, column 'temp_t1': 1e\+300 C is outside .*-100\.\.200")
    freq = lambda i, T: [i, 3.0, T, -1.0 if i == 3 else 4800.0]                        # noqa: E731
    _refused(db, _csv(tmp_path / "b.csv", header="time_s,gyro_x,temp_t1,freq_x", row=freq),
             r"line 6, column 'freq_x'.*must be positive")


def test_a_big_file_fails_late_and_leaves_nothing(db, tmp_path):
    """The problem is in the last batch: the earlier batches were read, none were stored."""
    late = lambda i, T: [i, 3.0, -2.0, 10.0, T, "x" if i == 2999 else T]              # noqa: E731
    path = _csv(tmp_path / "late.csv", n=3000, row=late)
    with pytest.raises(DataFormatError, match=r"line 3002, column 'temp_t2': not a number: 'x'"):
        import_csv(db, path, "G1", block_bytes=4096)
    _nothing_stored(db)


def test_store_failure_mid_import_removes_the_run(db, tmp_path, monkeypatch):
    """A failure while storing (here: the database refuses the 3rd batch) undoes the whole import."""
    from bench.storage import frames

    path = _csv(tmp_path / "ok.csv", n=3000)
    calls = {"n": 0}
    real = frames.FrameWriter.flush

    def failing_flush(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full")
        return real(self, *a, **k)

    monkeypatch.setattr(frames.FrameWriter, "flush", failing_flush)
    with pytest.raises(RuntimeError, match="disk full"):
        import_csv(db, path, "G1", block_bytes=4096)
    _nothing_stored(db)


def test_byte_order_mark_and_streamed_import_store_every_row(db, tmp_path):
    path = _csv(tmp_path / "bom.csv", n=3000, bom=True)
    assert CsvStream(path).header[0] == "time_s"
    assert read_csv(path).columns["time_s"].size == 3000
    rid = import_csv(db, path, "G1", block_bytes=4096)          # many batches
    ds = run_dataset(rid, db)
    assert len(ds) == 3000 and ds.meta["latitude_deg"] == "45.75"
    src = read_csv(path)
    assert np.allclose(ds["gyro_x"], src["gyro_x"], rtol=1e-6)      # float32 on the wire
    assert np.allclose(ds["temp_t2"], src["temp_t2"], atol=1e-9)


def test_missing_temperature_probe_and_missing_gyro(db, tmp_path):
    # no temp_t1: the import stores what is there, and static refuses instead of using temp_t2
    path = _csv(tmp_path / "t2.csv", header="time_s,gyro_x,gyro_y,gyro_z,temp_t2",
                row=lambda i, T: [i, 3.0 + 0.1 * T, -2.0, 10.0, T])
    rid = import_csv(db, path, "G1")
    with pytest.raises(DataFormatError, match=r"no temp_t1 .*temperature columns: temp_t2"):
        fit_model("static", run_dataset(rid, db), "x")
    assert fit_model("static", run_dataset(rid, db), "x", probe="t2").coefficients
    # no gyro and no frequency column: nothing measured, refused at the header
    with pytest.raises(DataFormatError, match=r"line 2: need at least one gyro_<ch> or freq_<ch> column \(columns: "
                                              r"time_s, temp_t1\)"):
        import_csv(db, _csv(tmp_path / "nogyro.csv", header="time_s,temp_t1", row=lambda i, T: [i, T]), "G2")
    with db.session() as s:
        assert s.scalar(select(func.count()).select_from(Run)) == 1


def test_frequency_table_without_gyro_columns_imports_and_fits_hrg_reverse(db, tmp_path):
    """The HRG paper's Table 1 as it is: temperature and resonance frequency, no gyro output."""
    temps = np.arange(-40.0, 51.0, 10.0)
    freq = 4800.0 + 0.47 * temps + 1e-4 * temps ** 2
    rows = [f"{k * 3600.0!r},{T!r},{f!r}" for k, (T, f) in enumerate(zip(temps.tolist(), freq.tolist()))]
    path = tmp_path / "table1.csv"
    path.write_text("# gyro_type: HRG\ntime_s,temp_t1,freq_x\n" + "\n".join(rows) + "\n")
    rid = import_csv(db, path, "HRG-1")
    ds = run_dataset(rid, db)
    assert "gyro_x" not in ds and np.allclose(ds["freq_x"], freq)
    res = fit_model("hrg_reverse", ds, "x", reference="t1")
    assert res.target == "temp_t1"
    with pytest.raises(DataFormatError, match=r"hrg on channel x: no gyro_x"):
        fit_model("hrg", ds, "x")


def test_cli_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("BENCH_DATABASE_URL", f"sqlite:///{tmp_path / 'cli.sqlite'}")
    res = runner.invoke(app, ["import", str(tmp_path / "nowhere.csv"), "--gyro", "G1"])
    assert res.exit_code == 2 and res.output.strip() == f"error: {tmp_path / 'nowhere.csv'}: file not found"
    res = runner.invoke(app, ["import", str(tmp_path), "--gyro", "G1"])
    assert res.exit_code == 2 and "is a directory" in res.output and len(res.output.strip().splitlines()) == 1
    big = _csv(tmp_path / "big.csv", row=lambda i, T: [i, 3.0, -2.0, 1e308, T, T])
    res = runner.invoke(app, ["import", str(big), "--gyro", "G1"])
    assert res.exit_code == 2 and "OverflowError" not in res.output and "gyro_z" in res.output
    deep = "(" * 3000 + "t1" + ")" * 3000
    good = _csv(tmp_path / "good.csv")
    res = runner.invoke(app, ["fit", deep, str(good), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 2 and "at most 300" in res.output and "RecursionError" not in res.output
    res = runner.invoke(app, ["fit", "t1^99999", str(good), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 2 and "exponent 99999 is above the limit of 9" in res.output
    res = runner.invoke(app, ["run", "thermal_ramp", "--gyro", "G1", "--sim", "--param", "soak_h=1e9"])
    assert res.exit_code == 2 and "soak_h" in res.output


def test_dataset_round_trip_through_the_csv_keeps_the_fit(db, tmp_path):
    """An in-memory dataset imported, exported, re-imported: the same fit."""
    from tests.test_api_http import synthetic_dataset

    ds = synthetic_dataset(n=600)
    ds.meta["latitude_deg"] = "30.0"
    src = tmp_path / "src.csv"
    write_csv(ds, src)
    rid = import_csv(db, src, "G1")
    exported = tmp_path / "exported.csv"
    write_csv(run_dataset(rid, db), exported)
    rid2 = import_csv(db, exported, "G1")
    a = fit_model("static", run_dataset(rid, db), "x")
    b = fit_model("static", read_csv(exported), "x")
    c = fit_model("static", run_dataset(rid2, db), "x")
    for other in (b, c):
        assert other.coefficients == pytest.approx(a.coefficients, rel=1e-9, abs=1e-9)
    assert a.definition["earth_rate"]["earth_rate_removed"] is True


def test_missing_latitude_with_known_orientation_fits_with_a_warning(tmp_path):
    """No latitude but an orientation: the fit says the Earth rate stays in the bias (the CLI prints it)."""
    from tests.test_api_http import synthetic_dataset

    ds = synthetic_dataset(n=600)
    ds.meta.pop("latitude_deg", None)
    res = fit_model("static", ds, "x")
    warning = res.definition["earth_rate"]["warning"]
    assert res.definition["earth_rate"]["earth_rate_removed"] is False and "latitude unknown" in warning
    path = tmp_path / "nolat.csv"
    write_csv(ds, path)
    out = runner.invoke(app, ["fit", "static", str(path), "--json", str(tmp_path / "o.json"), "--channel", "x"])
    assert out.exit_code == 0 and "warning: x: latitude unknown" in out.output
    # with the latitude, rows whose orientation is unknown are left out (and said so), not taken as NUE
    ds.meta["latitude_deg"] = "45.75"
    ds.columns["orientation"] = ds.columns["orientation"].astype(object)
    ds.columns["orientation"][:100] = ""
    res = fit_model("static", ds, "x")
    assert res.definition["earth_rate"]["earth_rate_removed"] is True
    assert "100 of 600 rows have no orientation" in res.definition["earth_rate"]["warning"]


def test_killed_import_leaves_a_staging_run_the_next_import_removes(tmp_path):
    """kill -9 while storing: the staging run (``live.import == "storing"``, host and pid) stays until the
    next import on this host, which deletes it with every row; then only the finished import remains."""
    import os
    import signal
    import subprocess
    import sys
    import time

    url = f"sqlite:///{tmp_path / 'kill.sqlite'}"
    db = open_database(url)
    big = _csv(tmp_path / "big.csv", n=3000)
    hold = tmp_path / "held"
    # the child imports with a FrameWriter whose 2nd flush parks until the test kills it: the kill is
    # known to land while storing, whatever the machine's load
    child = subprocess.Popen([sys.executable, "-c", f"""
import pathlib, time
from bench.storage import frames, open_database
from bench.commands.importing import import_csv
real, n = frames.FrameWriter.flush, [0]
def parked(self, *a, **k):
    n[0] += 1
    if n[0] == 2:
        pathlib.Path({str(hold)!r}).write_text("storing")
        while True:
            time.sleep(0.05)
    return real(self, *a, **k)
frames.FrameWriter.flush = parked
import_csv(open_database({url!r}), {str(big)!r}, "G1", block_bytes=4096)
"""], cwd=os.getcwd())
    try:
        for _ in range(1200):                       # bounded: at most 60 s for the child to reach the park
            if hold.exists() or child.poll() is not None:
                break
            time.sleep(0.05)
        assert hold.exists(), "the child import never reached its second batch"
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
    with db.session() as s:
        staged = s.scalars(select(Run)).all()
        assert [(r.procedure, r.status, (r.live or {}).get("import")) for r in staged] == [("import", "running", "storing")]
        assert s.scalar(select(func.count()).select_from(FrameChunk)) > 0     # it had written rows
    new_id = import_csv(db, _csv(tmp_path / "small.csv", n=300), "G2")
    with db.session() as s:
        runs = s.scalars(select(Run)).all()
        assert [(r.id, r.status) for r in runs] == [(new_id, "completed")]
        assert s.scalar(select(func.count()).select_from(FrameChunk).where(FrameChunk.run_id != new_id)) == 0
        assert s.scalar(select(func.count()).select_from(ProbeReadingRow).where(ProbeReadingRow.run_id != new_id)) == 0
    db.dispose()

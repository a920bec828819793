"""``bench fit`` and ``bench close-loop`` from the command line, on measured-data CSV files."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from bench.cli import app
from bench.fit.csvio import write_csv
from tests import REFERENCE_DIR
from tests.synth import TRAIN_PROFILE, VALIDATE_PROFILE, make_run

REFERENCE = REFERENCE_DIR / "hrg_frequency_temperature.csv"
runner = CliRunner()


def _table1_as_measured_csv(path: Path) -> None:
    """S002 Table 1 as a measured-data CSV: one row per 5-h soak point (frequency and DS18B20 per gyro)."""
    rows = [r for r in csv.reader(line for line in REFERENCE.read_text().splitlines() if not line.startswith("#"))]
    header, data = rows[0], rows[1:]
    col = {name: i for i, name in enumerate(header)}
    lines = ["# gyro_id: HRG-S002", "# gyro_type: hrg", "time_s,gyro_x,freq_x,temp_gx,chamber_sp"]
    for k, r in enumerate(data):
        lines.append(f"{k * 18000.0},,{r[col['freq_gx_hz']]},{r[col['ds18b20_gx_c']]},{r[col['chamber_c']]}")
    path.write_text("\n".join(lines) + "\n")


def test_hrg_reverse_reproduces_the_paper_from_the_cli(tmp_path):
    data = tmp_path / "table1.csv"
    _table1_as_measured_csv(data)
    out = tmp_path / "fit.json"
    res = runner.invoke(app, ["fit", "hrg_reverse", str(data), "--json", str(out), "--channel", "x"])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["channels"]["x"]["max_abs_error_c"] <= 0.03


def test_fit_static_json_has_the_documented_fields_and_html(tmp_path):
    train, _ = make_run(TRAIN_PROFILE, {}, seed=1)
    validate, _ = make_run(VALIDATE_PROFILE, {}, seed=2)
    write_csv(train, tmp_path / "train.csv")
    write_csv(validate, tmp_path / "val.csv")
    res = runner.invoke(app, ["fit", "static", str(tmp_path / "train.csv"), str(tmp_path / "val.csv"),
                              "--json", str(tmp_path / "fit.json"), "--html", str(tmp_path / "fit.html")])
    assert res.exit_code == 0, res.output
    ch = json.loads((tmp_path / "fit.json").read_text())["channels"]["x"]
    assert set(ch) >= {"coefficients", "validity", "train", "validation"}
    for part in ("train", "validation"):
        assert ch[part]["rms_dph"] > 0 and ch[part]["std100_dph"] > 0
    assert np.isclose(ch["coefficients"]["A1"], 0.02, rtol=0.05)
    page = (tmp_path / "fit.html").read_text()
    assert "<img" in page and "http://" not in page


def test_bad_formula_and_bad_csv_give_clear_errors(tmp_path):
    train, _ = make_run(TRAIN_PROFILE[:3], {}, seed=1)
    write_csv(train, tmp_path / "train.csv")
    res = runner.invoke(app, ["fit", "t1 + q9", str(tmp_path / "train.csv"), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 2 and "q9" in res.output
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,gyro_x,temp_t1\n0,1.0,20\n1,abc,20\n")
    res = runner.invoke(app, ["fit", "static", str(bad), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 2 and "line 3" in res.output and "gyro_x" in res.output
    assert not (tmp_path / "o.json").exists()


def test_close_loop_cli_writes_the_report(tmp_path):
    hidden = {"rate": 0.08}
    train, _ = make_run(TRAIN_PROFILE, hidden, seed=1)
    validate, _ = make_run(VALIDATE_PROFILE, hidden, seed=2)
    write_csv(train, tmp_path / "train.csv")
    write_csv(validate, tmp_path / "val.csv")
    res = runner.invoke(app, ["close-loop", str(tmp_path / "train.csv"), str(tmp_path / "val.csv"),
                              "--model", "static", "--json", str(tmp_path / "cl.json"),
                              "--html", str(tmp_path / "cl.html")])
    assert res.exit_code == 0, res.output
    ch = json.loads((tmp_path / "cl.json").read_text())["channels"]["x"]
    assert set(ch) >= {"declared_model", "noise_floor_dph", "before", "after", "effects_added", "verdict", "findings"}
    for part in ("before", "after"):
        assert set(ch[part]) >= {"train_rms_dph", "validation_rms_dph", "validation_std100_dph"}
    assert ch["verdict"] == "explained" and ch["effects_added"][0]["kind"] == "rate"
    page = (tmp_path / "cl.html").read_text()
    assert page.count("<img") >= 6 and "https://" not in page


def test_close_loop_cli_leaves_out_a_channel_a_run_never_measured_and_names_it(tmp_path):
    # gyro_y is a column of both runs but the validation run holds not one reading of it.  Before, y was
    # called "no effect missing" on the training run alone with every validation number "-" (measured)
    train, _ = make_run(TRAIN_PROFILE, {}, seed=1)
    validate, _ = make_run(VALIDATE_PROFILE, {}, seed=2)
    write_csv(train.with_columns(gyro_y=train["gyro_x"]), tmp_path / "train.csv")
    write_csv(validate.with_columns(gyro_y=np.full(len(validate), np.nan)), tmp_path / "val.csv")
    args = ["close-loop", str(tmp_path / "train.csv"), str(tmp_path / "val.csv"), "--model", "static",
            "--json", str(tmp_path / "cl.json")]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "cl.json").read_text())
    assert list(doc["channels"]) == ["x"]
    assert doc["channels_not_analysed"] == {"y": "column gyro_y missing from the validation data (no column, or not one reading)"}
    assert "y: not analysed: column gyro_y missing from the validation data" in res.output
    res = runner.invoke(app, args + ["--channel", "y"])       # asked for by name: a clear error
    assert res.exit_code != 0 and "channel 'y': column gyro_y missing from the validation data" in res.output
